"""SET_POSITION_TARGET_LOCAL_NED validation: accepted masks/frames, every refusal reason."""

from __future__ import annotations

import math
import struct

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mavlink_bridge.interfaces import VelocityCommand
from mavlink_bridge.validate import (
    MASK_VELOCITY,
    MASK_VELOCITY_YAW,
    MASK_VELOCITY_YAW_RATE,
    MAV_FRAME_BODY_NED,
    MAV_FRAME_LOCAL_NED,
    Reject,
    SetpointLimits,
    SetpointValidator,
    validate_velocity_setpoint,
)


def msg(frame: int = MAV_FRAME_LOCAL_NED, mask: int = MASK_VELOCITY_YAW_RATE,
        v: tuple[float, float, float] = (1.0, 2.0, -0.5), yaw: float = 0.0,
        yaw_rate: float = 0.25, target: tuple[int, int] = (1, 1)) -> object:
    """A real pymavlink message, round-tripped through the wire (float32)."""
    m = mavlink.MAVLink_set_position_target_local_ned_message(
        0, target[0], target[1], frame, mask, 0.0, 0.0, 0.0, *v, 0.0, 0.0, 0.0, yaw, yaw_rate)
    enc = mavlink.MAVLink(None, 245, 190)
    dec = mavlink.MAVLink(None)
    return dec.parse_buffer(m.pack(enc))[0]


def f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


def test_local_ned_velocity_yaw_rate_becomes_enu() -> None:
    v = SetpointValidator()
    cmd = v.validate(msg(v=(1.0, 2.0, -0.5), yaw_rate=0.3))
    assert cmd == VelocityCommand(2.0, 1.0, 0.5, f32(-0.3), False, None)
    assert v.accepted == 1 and v.total_rejected == 0


def test_body_ned_becomes_flu_body_horizontal() -> None:
    cmd = SetpointValidator().validate(msg(frame=MAV_FRAME_BODY_NED, v=(1.0, 0.5, 0.25),
                                           yaw_rate=-0.5))
    assert cmd == VelocityCommand(1.0, -0.5, -0.25, 0.5, True, None)


def test_velocity_yaw_and_velocity_only_masks() -> None:
    v = SetpointValidator()
    cmd = v.validate(msg(mask=MASK_VELOCITY_YAW, yaw=0.0, yaw_rate=math.nan))
    assert isinstance(cmd, VelocityCommand)  # yaw rate ignored, NaN there is fine
    assert cmd.yaw == pytest.approx(math.pi / 2) and cmd.yaw_rate == 0.0  # north = ENU 90 deg
    cmd = v.validate(msg(mask=MASK_VELOCITY, yaw=math.nan, yaw_rate=math.inf))
    assert isinstance(cmd, VelocityCommand) and cmd.yaw is None and cmd.yaw_rate == 0.0


@pytest.mark.parametrize("mask", [MASK_VELOCITY_YAW_RATE, MASK_VELOCITY_YAW, MASK_VELOCITY])
def test_force_set_bit_changes_nothing(mask: int) -> None:
    """FORCE_SET (0x200) only reinterprets the acceleration fields, which every supported
    mask ignores (PX4 ignores the bit too); MAVProxy's ``velocity`` sends 0x0FC7."""
    v = SetpointValidator()
    plain = v.validate(msg(frame=MAV_FRAME_BODY_NED, mask=mask, yaw=0.5))
    forced = v.validate(msg(frame=MAV_FRAME_BODY_NED, mask=mask | 0x200, yaw=0.5))
    assert isinstance(plain, VelocityCommand) and forced == plain
    assert v.accepted == 2 and v.total_rejected == 0


@pytest.mark.parametrize(("kwargs", "reason"), [
    ({"target": (2, 1)}, Reject.WRONG_TARGET),
    ({"target": (1, 5)}, Reject.WRONG_TARGET),
    ({"target": (0, 0)}, Reject.WRONG_TARGET),
    ({"frame": 0}, Reject.UNKNOWN_FRAME),  # MAV_FRAME_GLOBAL
    ({"frame": 9}, Reject.UNKNOWN_FRAME),  # MAV_FRAME_BODY_OFFSET_NED
    ({"frame": 200}, Reject.UNKNOWN_FRAME),
    ({"mask": 0x0FF8}, Reject.UNSUPPORTED_TYPE_MASK),  # position only
    ({"mask": 0}, Reject.UNSUPPORTED_TYPE_MASK),
    ({"mask": MASK_VELOCITY_YAW_RATE & ~0x40}, Reject.UNSUPPORTED_TYPE_MASK),  # uses ax
    ({"mask": 0x0FF8 | 0x200}, Reject.UNSUPPORTED_TYPE_MASK),  # position + FORCE_SET
    ({"v": (math.nan, 0.0, 0.0)}, Reject.NAN),
    ({"yaw_rate": math.nan}, Reject.NAN),
    ({"v": (0.0, 0.0, math.inf)}, Reject.INF),
    ({"yaw_rate": -math.inf}, Reject.INF),
    ({"mask": MASK_VELOCITY_YAW, "yaw": math.inf}, Reject.INF),
    ({"v": (15.0, 15.0, 0.0)}, Reject.OUT_OF_RANGE),  # 21.2 m/s > 20
    ({"yaw_rate": 11.0}, Reject.OUT_OF_RANGE),
    ({"mask": MASK_VELOCITY_YAW, "yaw": 7.0}, Reject.OUT_OF_RANGE),
])
def test_refusals_are_counted_per_reason(kwargs: dict, reason: Reject) -> None:
    v = SetpointValidator()
    assert v.validate(msg(**kwargs)) is reason
    assert v.validate(msg(**kwargs)) is reason
    assert v.rejected == {reason: 2} and v.accepted == 0


def test_target_component_zero_is_any_and_limits_configurable() -> None:
    assert isinstance(SetpointValidator().validate(msg(target=(1, 0))), VelocityCommand)
    v = SetpointValidator(system_id=3, component_id=1, limits=SetpointLimits(max_speed=2.0))
    assert v.validate(msg(target=(3, 1), v=(1.5, 1.5, 0.5))) == Reject.OUT_OF_RANGE
    assert isinstance(v.validate(msg(target=(3, 1), v=(1.0, 1.0, 0.0))), VelocityCommand)


def test_pure_function_on_plain_numbers() -> None:
    out = validate_velocity_setpoint(target_system=1, target_component=1, coordinate_frame=1,
                                     type_mask=MASK_VELOCITY_YAW_RATE, vx=0.0, vy=0.0, vz=-1.0,
                                     yaw=math.nan, yaw_rate=0.0)
    assert out == VelocityCommand(0.0, 0.0, 1.0, 0.0, False, None)
