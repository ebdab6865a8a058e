"""NAV_TAKEOFF's altitude, read as PX4 reads it (AMSL) with skyloop's relative extension.

The conversion (:func:`mavlink_bridge.vehicle_link.takeoff_altitude`) on its own; then a
pymavlink ground station on a :class:`~gcs_rig.GcsRig` (real UDP, real commander) doing
what QGroundControl's PX4 Takeoff does (``PX4FirmwarePlugin::guidedModeTakeoff``): while
the vehicle is disarmed, NAV_TAKEOFF with param1 -1, params 4-6 NaN and param7 = the
vehicle's AMSL altitude (GLOBAL_POSITION_INT.alt) + the relative altitude, and only once
that is ACCEPTED, ARM (the vehicle shows AUTO.TAKEOFF disarmed in between, then climbs);
its "start takeoff" (SET_MODE AUTO.TAKEOFF, then ARM); the same altitude sent armed; and
MIS_TAKEOFF_ALT as the sim applies it (the default for a NaN altitude, MAVSDK's
``action.takeoff()``).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from gcs_rig import DT, GcsRig, of_type
from pymavlink.dialects.v20 import common as M

from bus import params
from mavlink_bridge.gcs.telemetry import TelemetryReporter
from mavlink_bridge.modes import AUTO_LOITER, AUTO_TAKEOFF, BaseMode
from mavlink_bridge.vehicle_link import takeoff_altitude
from sitl.commander.machine import Commander, State
from sitl.node.vehicle_service import apply_param

NAN = math.nan


@pytest.mark.parametrize(("param7", "home_amsl", "expected"), [
    (NAN, 488.0, None),  # MAVSDK: the vehicle's default (MIS_TAKEOFF_ALT)
    (492.0, 488.0, 4.0),  # QGroundControl: home AMSL + 4 m
    (1204.5, 1200.0, 4.5),  # another origin
    (3.0, 488.0, 3.0),  # MAVProxy's "takeoff 3": at or below home AMSL -> relative
    (488.0, 488.0, 488.0),  # exactly home AMSL: relative (the commander refuses 488 m)
    (3.0, 0.0, 3.0),  # a home at sea level: both readings agree
    (-1.0, 488.0, -1.0),  # bad values pass through for the commander to refuse
    (math.inf, 488.0, math.inf),
])
def test_takeoff_altitude_conversion(param7: float, home_amsl: float,
                                     expected: float | None) -> None:
    assert takeoff_altitude(param7, home_amsl) == expected


def test_home_amsl_is_origin_plus_home_height() -> None:
    rep = TelemetryReporter(Commander(), (47.0, 8.0, 488.0))
    assert rep.home_amsl == 488.0  # no position yet: the origin's
    rep.set_home((5.0, -3.0, 12.0))
    assert rep.home_amsl == 500.0


def test_mis_takeoff_alt_is_the_commanders_default_takeoff_altitude() -> None:
    c = Commander()
    assert params.BY_NAME["MIS_TAKEOFF_ALT"].default == c.config.takeoff_altitude == 2.5
    assert apply_param("MIS_TAKEOFF_ALT", params.check("MIS_TAKEOFF_ALT", 4.0), c, None)
    assert c.arm(0.0).accepted and c.takeoff(0.0, None).accepted
    assert c.pop_events()[-1].text == "Takeoff to 4.0 m"
    with pytest.raises(ValueError, match="MIS_TAKEOFF_ALT"):
        params.check("MIS_TAKEOFF_ALT", 0.1)


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[GcsRig]:
    r = GcsRig(tmp_path / "p.json")
    yield r
    r.close()


def command(rig: GcsRig, cmd: int, *params7: float) -> list[Any]:
    return rig.exchange(M.MAVLink_command_long_message(1, 1, cmd, 0, *params7))


def ack(got: list[Any]) -> int:
    return of_type(got, "COMMAND_ACK")[0].result


def heartbeat(got: list[Any]) -> Any:
    return of_type(got, "HEARTBEAT")[-1]


def armed(hb: Any) -> bool:
    return bool(hb.base_mode & BaseMode.SAFETY_ARMED)


def climb_to_hold(rig: GcsRig) -> None:
    for _ in range(int(20.0 / DT)):
        if rig.commander.state == State.HOLD:
            return
        rig.tick()
    raise AssertionError(f"takeoff not complete: {rig.commander.state}, z {rig.pos[2]:.2f}")


def test_qgc_takeoff_while_disarmed_waits_for_arming_then_climbs(rig: GcsRig) -> None:
    """QGroundControl's PX4 Takeoff, message for message."""
    got = rig.exchange(ticks=60)  # > 1 s: every telemetry stream once
    amsl = of_type(got, "GLOBAL_POSITION_INT")[-1].alt / 1000.0  # vehicle->altitudeAMSL()
    assert amsl == 488.0 and not armed(heartbeat(got))
    assert of_type(got, "EXTENDED_SYS_STATE")[-1].landed_state == M.MAV_LANDED_STATE_ON_GROUND
    got = command(rig, M.MAV_CMD_NAV_TAKEOFF, -1, 0, 0, NAN, NAN, NAN, amsl + 3.0)
    assert ack(got) == M.MAV_RESULT_ACCEPTED  # QGC arms only after this
    hb = heartbeat(got)  # sent at once on the mode change
    assert hb.custom_mode == AUTO_TAKEOFF.custom_mode and not armed(hb)
    assert hb.system_status == M.MAV_STATE_STANDBY
    assert "Takeoff pending: 3.0 m, arm to start" in [m.text for m in of_type(got, "STATUSTEXT")]
    got = rig.exchange(ticks=60)  # waiting on the ground, still AUTO.TAKEOFF, disarmed
    assert rig.pos[2] == 0.0 and heartbeat(got).custom_mode == AUTO_TAKEOFF.custom_mode
    assert of_type(got, "EXTENDED_SYS_STATE")[-1].landed_state == M.MAV_LANDED_STATE_ON_GROUND
    got = command(rig, M.MAV_CMD_COMPONENT_ARM_DISARM, 1, 0, 0, 0, 0, 0, 0)
    assert ack(got) == M.MAV_RESULT_ACCEPTED
    hb = heartbeat(got)
    assert hb.custom_mode == AUTO_TAKEOFF.custom_mode and armed(hb)
    assert [m.text for m in of_type(got, "STATUSTEXT")] == ["Armed", "Takeoff to 3.0 m"]
    climb_to_hold(rig)
    assert 2.9 <= rig.pos[2] <= 3.0
    got = rig.exchange(ticks=5)
    assert heartbeat(got).custom_mode == AUTO_LOITER.custom_mode and armed(heartbeat(got))
    assert of_type(got, "GLOBAL_POSITION_INT")[-1].relative_alt == pytest.approx(3000, abs=100)


def test_qgc_takeoff_reads_amsl_against_where_the_vehicle_stands(rig: GcsRig) -> None:
    """Home moves to the vehicle at arming, which QGroundControl's Takeoff does after
    NAV_TAKEOFF: a stale home (10 m above the vehicle here, as after landing lower down)
    must not change the altitude flown."""
    rig.link.set_home((0.0, 0.0, 10.0))
    amsl = of_type(rig.exchange(ticks=15), "GLOBAL_POSITION_INT")[-1].alt / 1000.0
    assert amsl == 488.0 and rig.link.reporter.home_amsl == 498.0
    got = command(rig, M.MAV_CMD_NAV_TAKEOFF, -1, 0, 0, NAN, NAN, NAN, amsl + 3.0)
    assert ack(got) == M.MAV_RESULT_ACCEPTED and rig.commander.pending_takeoff == 3.0


def test_qgc_start_takeoff_mode_then_arm_climbs_mis_takeoff_alt(rig: GcsRig) -> None:
    """QGroundControl's startTakeoff: SET_MODE AUTO.TAKEOFF, wait for the heartbeat, arm."""
    got = rig.exchange(M.MAVLink_set_mode_message(1, BaseMode.CUSTOM_MODE_ENABLED,
                                                  AUTO_TAKEOFF.custom_mode))
    hb = heartbeat(got)
    assert hb.custom_mode == AUTO_TAKEOFF.custom_mode and not armed(hb)
    assert ack(command(rig, M.MAV_CMD_COMPONENT_ARM_DISARM, 1, 0, 0, 0, 0, 0, 0)) == \
        M.MAV_RESULT_ACCEPTED
    climb_to_hold(rig)
    assert 2.4 <= rig.pos[2] <= 2.5  # MIS_TAKEOFF_ALT's default


def test_a_cancelled_pending_takeoff_reports_hold_and_arming_does_not_climb(
        rig: GcsRig) -> None:
    amsl = of_type(rig.exchange(ticks=15), "GLOBAL_POSITION_INT")[-1].alt / 1000.0
    assert ack(command(rig, M.MAV_CMD_NAV_TAKEOFF, -1, 0, 0, NAN, NAN, NAN, amsl + 3.0)) == \
        M.MAV_RESULT_ACCEPTED
    got = rig.exchange(M.MAVLink_set_mode_message(1, BaseMode.CUSTOM_MODE_ENABLED,
                                                  AUTO_LOITER.custom_mode))  # QGC's Hold
    assert heartbeat(got).custom_mode == AUTO_LOITER.custom_mode
    assert "Takeoff cancelled" in [m.text for m in of_type(got, "STATUSTEXT")]
    assert ack(command(rig, M.MAV_CMD_COMPONENT_ARM_DISARM, 1, 0, 0, 0, 0, 0, 0)) == \
        M.MAV_RESULT_ACCEPTED
    rig.exchange(ticks=50)
    assert rig.pos[2] == 0.0 and rig.commander.state == State.ARMED


def test_qgc_amsl_takeoff_after_arming_climbs_the_relative_altitude(rig: GcsRig) -> None:
    amsl = of_type(rig.exchange(ticks=5), "GLOBAL_POSITION_INT")[-1].alt / 1000.0
    assert amsl == 488.0  # QGroundControl's vehicle->altitudeAMSL()
    assert ack(command(rig, M.MAV_CMD_COMPONENT_ARM_DISARM, 1, 0, 0, 0, 0, 0, 0)) == \
        M.MAV_RESULT_ACCEPTED
    too_high = command(rig, M.MAV_CMD_NAV_TAKEOFF, -1, 0, 0, NAN, NAN, NAN, amsl + 150.0)
    assert ack(too_high) == M.MAV_RESULT_DENIED  # 150 m above home: refused, said why
    assert "Takeoff denied: bad altitude" in [m.text for m in of_type(too_high, "STATUSTEXT")]
    got = command(rig, M.MAV_CMD_NAV_TAKEOFF, -1, 0, 0, NAN, NAN, NAN, amsl + 4.0)
    assert ack(got) == M.MAV_RESULT_ACCEPTED
    assert "Takeoff to 4.0 m" in [m.text for m in of_type(got, "STATUSTEXT")]
    climb_to_hold(rig)
    assert 3.9 <= rig.pos[2] <= 4.0
    gpi = of_type(rig.exchange(ticks=5), "GLOBAL_POSITION_INT")[-1]
    assert gpi.relative_alt == pytest.approx(4000, abs=100)
