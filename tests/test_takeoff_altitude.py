"""NAV_TAKEOFF's altitude, read as PX4 reads it (AMSL) with skyloop's relative extension.

The conversion (:func:`mavlink_bridge.vehicle_link.takeoff_altitude`) on its own; then a
pymavlink ground station on a :class:`~gcs_rig.GcsRig` (real UDP, real commander) doing
what QGroundControl's PX4 takeoff does once the vehicle is armed: param7 = the vehicle's
AMSL altitude (GLOBAL_POSITION_INT.alt) + the relative altitude; and MIS_TAKEOFF_ALT as
the sim applies it (the default for a NaN altitude, MAVSDK's ``action.takeoff()``).
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
from mavlink_bridge.telemetry import TelemetryReporter
from mavlink_bridge.vehicle_link import takeoff_altitude
from sitl.commander import Commander, State
from sitl.vehicle_service import apply_param

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
    for _ in range(int(20.0 / DT)):
        if rig.commander.state == State.HOLD:
            break
        rig.tick()
    assert rig.commander.state == State.HOLD  # takeoff complete
    assert 3.9 <= rig.pos[2] <= 4.0
    gpi = of_type(rig.exchange(ticks=5), "GLOBAL_POSITION_INT")[-1]
    assert gpi.relative_alt == pytest.approx(4000, abs=100)
