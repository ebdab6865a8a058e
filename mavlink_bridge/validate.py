"""Validation of SET_POSITION_TARGET_LOCAL_NED velocity setpoints.

Supported type masks (a set bit means "ignore this field"); anything else is refused as
``UNSUPPORTED_TYPE_MASK``::

    0x05C7 (1479)  velocity + yaw rate   (MAVSDK's body velocity; what our policy sends)
    0x09C7 (2503)  velocity + yaw        (MAVSDK's NED velocity; yaw is an absolute heading)
    0x0DC7 (3527)  velocity only         (ArduPilot's "use velocity"; yaw rate 0)

each also with the FORCE_SET bit (0x200, "acceleration fields are a force"): all three
ignore the acceleration fields, so the bit changes nothing, and PX4 ignores it too.
MAVProxy's ``velocity x y z`` sends 0x0FC7 (4039) = velocity only + FORCE_SET.

Frames: ``MAV_FRAME_LOCAL_NED`` (1) -> world ENU; ``MAV_FRAME_BODY_NED`` (8) ->
body-horizontal FLU (forward, left, up), ``frame_is_body=True``: the consumer rotates it
by the vehicle's current heading (PX4 treats BODY_NED velocities the same way, heading
only). An absolute yaw is always a world heading (converted NED -> ENU). The conversion
is done once, here, through :mod:`mavlink_bridge.frames`.

Refusals, checked in this order, each with a :class:`Reject` code counted by
:class:`SetpointValidator`: wrong target system/component (the component may be 0,
"any"), unknown frame, unsupported type mask, NaN, inf, out of range (speed norm above
``max_speed``, ``|yaw_rate|`` above ``max_yaw_rate``, ``|yaw|`` above 2 pi). Only the
fields the mask uses are checked: ignored fields may hold anything, NaN included.
Saturation to the flight envelope is the autopilot's job; this only refuses the absurd.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from mavlink_bridge import frames
from mavlink_bridge.interfaces import VelocityCommand

log = logging.getLogger(__name__)

MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_NED = 8

MASK_VELOCITY_YAW_RATE = 0x05C7
MASK_VELOCITY_YAW = 0x09C7
MASK_VELOCITY = 0x0DC7
SUPPORTED_MASKS = frozenset({MASK_VELOCITY_YAW_RATE, MASK_VELOCITY_YAW, MASK_VELOCITY})
FORCE_SET = 0x200  # POSITION_TARGET_TYPEMASK_FORCE_SET: moot when accelerations are ignored


def supported_mask(type_mask: int) -> int | None:
    """The supported mask ``type_mask`` means (FORCE_SET cleared), or None."""
    base = type_mask & ~FORCE_SET
    return base if base in SUPPORTED_MASKS else None


class Reject(StrEnum):
    """Why a setpoint was refused."""

    WRONG_TARGET = "wrong_target"
    UNKNOWN_FRAME = "unknown_frame"
    UNSUPPORTED_TYPE_MASK = "unsupported_type_mask"
    NAN = "nan"
    INF = "inf"
    OUT_OF_RANGE = "out_of_range"


@dataclass(frozen=True)
class SetpointLimits:
    """What is absurd (refused), not what is flown (the autopilot saturates)."""

    max_speed: float = 20.0  # m/s, norm of (vx, vy, vz)
    max_yaw_rate: float = 10.0  # rad/s


def validate_velocity_setpoint(
    *, target_system: int, target_component: int, coordinate_frame: int, type_mask: int,
    vx: float, vy: float, vz: float, yaw: float, yaw_rate: float,
    system_id: int = 1, component_id: int = 1, limits: SetpointLimits | None = None,
) -> VelocityCommand | Reject:
    """Check one SET_POSITION_TARGET_LOCAL_NED's fields; a command in skyloop's frames
    (see the module docstring) or the reason it is refused. Pure: no counters, no log."""
    lim = limits or SetpointLimits()
    if target_system != system_id or target_component not in (0, component_id):
        return Reject.WRONG_TARGET
    if coordinate_frame not in (MAV_FRAME_LOCAL_NED, MAV_FRAME_BODY_NED):
        return Reject.UNKNOWN_FRAME
    mask = supported_mask(type_mask)
    if mask is None:
        return Reject.UNSUPPORTED_TYPE_MASK
    type_mask = mask
    used = [vx, vy, vz]
    if type_mask == MASK_VELOCITY_YAW_RATE:
        used.append(yaw_rate)
    elif type_mask == MASK_VELOCITY_YAW:
        used.append(yaw)
    if any(math.isnan(v) for v in used):
        return Reject.NAN
    if any(math.isinf(v) for v in used):
        return Reject.INF
    if math.sqrt(vx * vx + vy * vy + vz * vz) > lim.max_speed:
        return Reject.OUT_OF_RANGE
    rate = yaw_rate if type_mask == MASK_VELOCITY_YAW_RATE else 0.0
    if abs(rate) > lim.max_yaw_rate:
        return Reject.OUT_OF_RANGE
    if type_mask == MASK_VELOCITY_YAW and abs(yaw) > 2.0 * math.pi:
        return Reject.OUT_OF_RANGE
    body = coordinate_frame == MAV_FRAME_BODY_NED
    convert = frames.velocity_body_ned_to_flu if body else frames.velocity_local_ned_to_enu
    ex, ey, ez, erate = convert(float(vx), float(vy), float(vz), float(rate))
    heading = frames.yaw_ned_to_enu(float(yaw)) if type_mask == MASK_VELOCITY_YAW else None
    return VelocityCommand(ex, ey, ez, erate + 0.0, body, heading)


class SetpointValidator:
    """:func:`validate_velocity_setpoint` with a counter per reason and a rate-limited log
    (a reason's 1st, 2nd, 4th, 8th, ... refusal is logged)."""

    def __init__(self, system_id: int = 1, component_id: int = 1,
                 limits: SetpointLimits | None = None) -> None:
        self.system_id = system_id
        self.component_id = component_id
        self.limits = limits or SetpointLimits()
        self.rejected: Counter[Reject] = Counter()
        self.accepted = 0

    def validate(self, msg: Any) -> VelocityCommand | Reject:
        """Validate a decoded SET_POSITION_TARGET_LOCAL_NED (anything with its fields)."""
        result = validate_velocity_setpoint(
            target_system=msg.target_system, target_component=msg.target_component,
            coordinate_frame=msg.coordinate_frame, type_mask=msg.type_mask,
            vx=msg.vx, vy=msg.vy, vz=msg.vz, yaw=msg.yaw, yaw_rate=msg.yaw_rate,
            system_id=self.system_id, component_id=self.component_id, limits=self.limits)
        if isinstance(result, Reject):
            self.rejected[result] += 1
            n = self.rejected[result]
            if n & (n - 1) == 0:
                log.warning("setpoint rejected (%s, %d so far): frame %s mask 0x%04X "
                            "v=(%r, %r, %r) yaw=%r yaw_rate=%r target %s/%s", result.value, n,
                            msg.coordinate_frame, msg.type_mask, msg.vx, msg.vy, msg.vz,
                            msg.yaw, msg.yaw_rate, msg.target_system, msg.target_component)
        else:
            self.accepted += 1
        return result

    @property
    def total_rejected(self) -> int:
        return sum(self.rejected.values())
