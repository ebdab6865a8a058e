"""The telemetry set a ground station / MAVSDK reads, its rates, TIMESYNC; real UDP.

Counts are over simulated time (ticks of tests/gcs_rig.DT), never wall time.
"""

from __future__ import annotations

import math
import socket
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from gcs_rig import DT, GcsRig, of_type
from pymavlink.dialects.v20 import common as M

from mavlink_bridge import frames
from mavlink_bridge.gcs.telemetry import BatteryModel, TelemetryReporter
from mavlink_bridge.vehicle_link import LinkConfig

ORIGIN = (47.397742, 8.545594, 488.0)
STREAMS = ["HEARTBEAT", "SYS_STATUS", "EXTENDED_SYS_STATE", "HOME_POSITION", "GPS_RAW_INT",
           "ATTITUDE", "ATTITUDE_QUATERNION", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT",
           "VFR_HUD", "BATTERY_STATUS", "MISSION_CURRENT"]
SENSORS = (M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL
           | M.MAV_SYS_STATUS_GEOFENCE
           | M.MAV_SYS_STATUS_SENSOR_3D_MAG | M.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
           | M.MAV_SYS_STATUS_SENSOR_GPS)


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[GcsRig]:
    r = GcsRig(tmp_path / "p.json")
    yield r
    r.close()


def ticks(seconds: float) -> int:
    return int(round(seconds / DT))


def command(rig: GcsRig, cmd: int, *params: float) -> list[Any]:
    p = list(params) + [0.0] * (7 - len(params))
    got = rig.exchange(M.MAVLink_command_long_message(1, 1, cmd, 0, *p))
    return got


def last(msgs: list[Any], kind: str) -> Any:
    found = of_type(msgs, kind)
    assert found, f"no {kind}"
    return found[-1]


def test_every_stream_arrives_with_sane_contents(rig: GcsRig) -> None:
    rig.vel[0], rig.vel[1] = 1.0, 1.0  # moving north-east (reported only)
    got = rig.exchange(ticks=ticks(2.5))
    counts = Counter(m.get_type() for m in got)
    assert all(counts[k] >= 1 for k in STREAMS), counts
    sys_status = last(got, "SYS_STATUS")
    for field in ("present", "enabled", "health"):
        bits = getattr(sys_status, f"onboard_control_sensors_{field}")
        assert bits & SENSORS == SENSORS and bits & M.MAV_SYS_STATUS_PREARM_CHECK, field
    assert 16000 < sys_status.voltage_battery <= 16800 and sys_status.battery_remaining == 100
    assert last(got, "EXTENDED_SYS_STATE").landed_state == M.MAV_LANDED_STATE_ON_GROUND
    gps = last(got, "GPS_RAW_INT")
    assert gps.fix_type >= 3 and gps.satellites_visible >= 8
    assert gps.vel == round(math.sqrt(2) * 100) and gps.cog == 4500  # north-east
    # GLOBAL_POSITION_INT matches LOCAL_POSITION_NED through the origin.
    gpi, lpn = last(got, "GLOBAL_POSITION_INT"), last(got, "LOCAL_POSITION_NED")
    east, north, up = frames.geodetic_to_enu(gpi.lat / 1e7, gpi.lon / 1e7, gpi.alt / 1000,
                                             ORIGIN)
    assert (north, east, -up) == pytest.approx((lpn.x, lpn.y, lpn.z), abs=0.02)
    assert (lpn.x, lpn.y) == (4.0, 3.0) and gpi.relative_alt == 0
    assert (gpi.vx, gpi.vy, gpi.vz) == (100, 100, 0)
    assert gpi.hdg == round(math.degrees(frames.yaw_enu_to_ned(0.3)) * 100) % 36000
    assert (gps.lat, gps.lon) == (gpi.lat, gpi.lon)
    # HOME_POSITION: the first position, in both frames.
    home = last(got, "HOME_POSITION")
    assert (home.latitude, home.longitude, home.altitude) == (gpi.lat, gpi.lon, 488000)
    assert (home.x, home.y, home.z) == (4.0, 3.0, 0.0)
    # ATTITUDE_QUATERNION is ATTITUDE.
    att, aq = last(got, "ATTITUDE"), last(got, "ATTITUDE_QUATERNION")
    assert frames.euler_from_quat((aq.q1, aq.q2, aq.q3, aq.q4)) == pytest.approx(
        (att.roll, att.pitch, att.yaw), abs=1e-5)
    assert att.pitch == pytest.approx(0.1) and (aq.rollspeed, aq.yawspeed) == pytest.approx(
        (0.01, -0.03))
    hud = last(got, "VFR_HUD")
    assert hud.heading == gpi.hdg // 100 and hud.alt == pytest.approx(488.0)
    assert hud.groundspeed == pytest.approx(math.sqrt(2), rel=1e-6) and hud.throttle == 0
    bat = last(got, "BATTERY_STATUS")
    assert len(set(bat.voltages[:4])) == 1  # 4 cells, equal
    assert abs(bat.voltages[0] * 4 - sys_status.voltage_battery) <= 4
    assert bat.voltages[4] == 65535 and bat.battery_remaining == 100
    assert bat.charge_state == M.MAV_BATTERY_CHARGE_STATE_OK
    assert last(got, "MISSION_CURRENT").mission_state == M.MISSION_STATE_NO_MISSION


def test_flight_landed_states_home_at_arming_battery_drains(rig: GcsRig) -> None:
    rig.pos[0] = 10.0  # the vehicle moved on the ground before arming: home follows it
    rig.tick()
    got = command(rig, M.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert of_type(got, "COMMAND_ACK")[0].result == M.MAV_RESULT_ACCEPTED
    assert last(got, "HOME_POSITION").y == 10.0  # sent at once, east = NED y
    command(rig, M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 3.0)
    got = rig.exchange(ticks=ticks(1.0))
    assert last(got, "EXTENDED_SYS_STATE").landed_state == M.MAV_LANDED_STATE_TAKEOFF
    got = rig.exchange(ticks=ticks(60.0))
    assert last(got, "EXTENDED_SYS_STATE").landed_state == M.MAV_LANDED_STATE_IN_AIR
    gpi, hb = last(got, "GLOBAL_POSITION_INT"), last(got, "HEARTBEAT")
    assert gpi.relative_alt == pytest.approx(3000, abs=150) and hb.system_status == \
        M.MAV_STATE_ACTIVE
    bat = last(got, "BATTERY_STATUS")  # ~61 s armed at 15 A of 5000 mAh: ~5 % used
    assert 93 <= bat.battery_remaining <= 96 and bat.current_battery == 1500
    assert last(got, "VFR_HUD").throttle == 50
    command(rig, M.MAV_CMD_NAV_LAND)
    got = rig.exchange(ticks=ticks(1.5))
    assert last(got, "EXTENDED_SYS_STATE").landed_state == M.MAV_LANDED_STATE_LANDING
    got = rig.exchange(ticks=ticks(10.0))
    assert last(got, "EXTENDED_SYS_STATE").landed_state == M.MAV_LANDED_STATE_ON_GROUND
    assert not last(got, "HEARTBEAT").base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED


def count_over(rig: GcsRig, kind: str, seconds: float) -> int:
    return len(of_type(rig.exchange(ticks=ticks(seconds)), kind))


def test_set_message_interval_changes_the_rate_on_that_link(rig: GcsRig) -> None:
    gpi = M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT
    assert count_over(rig, "GLOBAL_POSITION_INT", 4.0) in (19, 20, 21)  # default 5 Hz
    ack = of_type(command(rig, M.MAV_CMD_SET_MESSAGE_INTERVAL, gpi, 40000), "COMMAND_ACK")
    assert ack[0].result == M.MAV_RESULT_ACCEPTED
    assert count_over(rig, "GLOBAL_POSITION_INT", 4.0) in (99, 100, 101)  # 25 Hz
    got = command(rig, M.MAV_CMD_GET_MESSAGE_INTERVAL, gpi)
    assert [m.get_type() for m in got if m.get_type() in ("COMMAND_ACK", "MESSAGE_INTERVAL")] \
        == ["COMMAND_ACK", "MESSAGE_INTERVAL"]
    mi = last(got, "MESSAGE_INTERVAL")
    assert (mi.message_id, mi.interval_us) == (gpi, 40000)
    command(rig, M.MAV_CMD_SET_MESSAGE_INTERVAL, gpi, -1)
    assert count_over(rig, "GLOBAL_POSITION_INT", 3.0) == 0
    assert last(command(rig, M.MAV_CMD_GET_MESSAGE_INTERVAL, gpi),
                "MESSAGE_INTERVAL").interval_us == -1
    command(rig, M.MAV_CMD_SET_MESSAGE_INTERVAL, gpi, 0)  # back to the default
    assert count_over(rig, "GLOBAL_POSITION_INT", 4.0) in (19, 20, 21)
    # A message that is not streamed by default can be: AUTOPILOT_VERSION at 1 Hz.
    command(rig, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 1e6)
    assert count_over(rig, "AUTOPILOT_VERSION", 4.0) in (3, 4, 5)
    # The heartbeat too.
    command(rig, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_HEARTBEAT, 250000)
    assert count_over(rig, "HEARTBEAT", 4.0) in (15, 16, 17)
    # Refusals: unknown id, meaningless interval.
    for params, result in (((9999, 1e5), M.MAV_RESULT_UNSUPPORTED),
                           ((math.nan, 1e5), M.MAV_RESULT_UNSUPPORTED),
                           ((gpi, -5), M.MAV_RESULT_DENIED),
                           ((gpi, math.nan), M.MAV_RESULT_DENIED)):
        ack = of_type(command(rig, M.MAV_CMD_SET_MESSAGE_INTERVAL, *params), "COMMAND_ACK")
        assert ack[0].result == result, params
    ack = of_type(command(rig, M.MAV_CMD_GET_MESSAGE_INTERVAL, 9999), "COMMAND_ACK")
    assert ack[0].result == M.MAV_RESULT_UNSUPPORTED
    assert rig.link.counters["message_interval.unsupported"] == 3


def test_rates_are_per_link(tmp_path: Path) -> None:
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    rig = GcsRig(tmp_path / "p.json", api=LinkConfig(0, sink.getsockname()[1]))
    try:
        command(rig, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_VFR_HUD, -1)
        assert count_over(rig, "VFR_HUD", 2.0) == 0
        assert rig.link.rates["api"].interval_us(M.MAVLINK_MSG_ID_VFR_HUD) == 250000
        assert rig.link.rates["gcs"].interval_us(M.MAVLINK_MSG_ID_VFR_HUD) == -1
    finally:
        rig.close()
        sink.close()


def test_timesync_and_request_message_home(rig: GcsRig) -> None:
    rig.tick(7)
    got = rig.exchange(M.MAVLink_timesync_message(0, 123456789))
    (ts,) = of_type(got, "TIMESYNC")
    assert ts.ts1 == 123456789 and ts.tc1 == round(rig.now * 1e9)
    assert not of_type(rig.exchange(M.MAVLink_timesync_message(5, 6)), "TIMESYNC")
    assert rig.link.counters["timesync.ignored"] == 1
    got = command(rig, M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HOME_POSITION)
    kinds = [m.get_type() for m in got if m.get_type() in ("COMMAND_ACK", "HOME_POSITION")]
    assert kinds == ["COMMAND_ACK", "HOME_POSITION"]
    # Before any telemetry there is no home: TEMPORARILY_REJECTED (MAVSDK asks again).
    reporter = TelemetryReporter(rig.commander, ORIGIN)
    assert reporter.home_position() is None and reporter.global_position_int() is None


def test_battery_model_drains_with_armed_time_only() -> None:
    b = BatteryModel()
    b.step(0.0, armed=False)
    b.step(600.0, armed=False)  # 10 min idle at 0.5 A: 83 mAh
    assert b.drawn_mah == pytest.approx(0.5 * 600 / 3.6)
    b.step(500.0, armed=True)  # time going back adds nothing
    assert b.drawn_mah == pytest.approx(0.5 * 600 / 3.6)
    b.step(1800.0, armed=True)  # 20 min at 15 A (+ the idle draw): empty
    assert b.remaining == 0.0 and b.charge_state == M.MAV_BATTERY_CHARGE_STATE_EMERGENCY
    assert b.voltage == pytest.approx(4 * 3.5 - 0.02 * 15)
    assert BatteryModel().voltage == pytest.approx(16.8 - 0.01)
