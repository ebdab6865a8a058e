"""Goals from a ground station (mavlink_bridge.gcs.goals): the pure conversion and queue,
then DO_REPOSITION, SET_POSITION_TARGET_GLOBAL_INT and a mission started by DO_SET_MODE
AUTO.MISSION from a pymavlink ground station over real UDP (tests/gcs_rig.py: a real
Commander on a point vehicle), progress driven by real episode event messages."""

from __future__ import annotations

import math
import random
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from gcs_rig import GcsRig, of_type
from pymavlink.dialects.v20 import common as M
from test_mavlink_missions import item, upload

from bus import messages as bm
from mavlink_bridge import frames
from mavlink_bridge.gcs.goals import (
    Goal,
    GoalFrame,
    GoalQueue,
    GoalService,
    goal_position,
    plan_mission,
)
from mavlink_bridge.gcs.missions import MissionItem, item_from_message

ORIGIN = (47.397742, 8.545594, 488.0)
HOME = (3.0, 4.0, 0.5)
FRAME = GoalFrame(ORIGIN, HOME, flight_level=3.5, geofence=60.0)
REL = M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT


def lat_lon(x: float, y: float) -> tuple[float, float]:
    lat, lon, _ = frames.enu_to_geodetic(x, y, 0.0, ORIGIN)
    return lat, lon


def wp(x: float, y: float, alt: float, frame: int = REL, seq: int = 0,
       command: int = M.MAV_CMD_NAV_WAYPOINT) -> MissionItem:
    it = item_from_message(item(seq, command, *lat_lon(x, y), alt, frame=frame))
    assert isinstance(it, MissionItem)
    return it


# ---------------------------------------------------------------------------- pure
def test_goal_position_frames_altitudes_and_refusals() -> None:
    assert goal_position(wp(10.0, -5.0, 3.0), FRAME) == pytest.approx((10.0, -5.0, 3.5),
                                                                      abs=0.02)
    # Relative altitude 0 (the ground under home): the flight level above the datum.
    assert goal_position(wp(10.0, -5.0, 0.0), FRAME) == pytest.approx((10.0, -5.0, 3.5),
                                                                      abs=0.02)
    amsl = wp(10.0, -5.0, 492.0, frame=M.MAV_FRAME_GLOBAL_INT)
    assert goal_position(amsl, FRAME) == pytest.approx((10.0, -5.0, 4.0), abs=0.02)
    nan_alt = wp(10.0, -5.0, math.nan)
    assert goal_position(nan_alt, FRAME, current_z=2.7) == pytest.approx((10.0, -5.0, 2.7),
                                                                         abs=0.02)
    assert goal_position(nan_alt, FRAME) == "bad_altitude"
    local = MissionItem(0, M.MAV_FRAME_LOCAL_ENU, M.MAV_CMD_NAV_WAYPOINT, 1, 0, 0, 0, 0,
                        120000, -50000, 3.0, 0)
    assert goal_position(local, FRAME) == (12.0, -5.0, 3.0)
    bad_lat = MissionItem(0, REL, M.MAV_CMD_NAV_WAYPOINT, 1, 0, 0, 0, 0, 910_000_000, 0,
                          3.0, 0)
    assert goal_position(bad_lat, FRAME) == "bad_latitude"
    assert goal_position(bad_lat.__class__(**{**bad_lat.__dict__, "x": 0,
                                              "y": 1_810_000_000}), FRAME) == "bad_longitude"
    assert goal_position(wp(70.0, 4.0, 3.0), FRAME) == "beyond_geofence"  # 67 m from home
    no_fence = GoalFrame(ORIGIN, HOME, 3.5, 0.0)
    assert goal_position(wp(70.0, 4.0, 3.0), no_fence) == pytest.approx((70.0, 4.0, 3.5),
                                                                        abs=0.02)
    terrain = wp(1.0, 1.0, 3.0, frame=M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT)
    assert goal_position(terrain, FRAME) == "unsupported_frame"


def test_plan_and_queue_one_goal_after_another() -> None:
    items = [wp(0, 0, 2.0, seq=0, command=M.MAV_CMD_NAV_TAKEOFF), wp(10, 0, 3.0, seq=1),
             wp(10, 10, 3.0, seq=2), wp(0, 0, 0.0, seq=3, command=M.MAV_CMD_NAV_LAND)]
    plan = plan_mission(items, FRAME)
    assert isinstance(plan, list)
    assert [g.kind for g in plan] == ["pass", "goal", "goal", "land"]
    assert plan_mission([wp(0, 0, 3.0), wp(500, 0, 3.0, seq=1)], FRAME) == \
        (1, "beyond_geofence")
    q = GoalQueue()
    ev = q.start(plan)
    assert [(w, g.seq if g else None) for w, g in ev] == [
        ("current", 0), ("pass", 0), ("reached", 0), ("current", 1), ("goal", 1)]
    g1 = plan[1].position
    assert q.on_end(7, "success") == []  # not started toward our goal yet
    q.on_start(7, (55.0, 5.0))  # someone else's goal: not ours
    q.on_start(8, (g1[0], g1[1]))
    assert q.on_end(7, "aborted") == []
    ev = q.on_end(8, "success")
    assert [(w, g.seq) for w, g in ev] == [("reached", 1), ("current", 2), ("goal", 2)]
    q.on_start(9, plan[2].position[:2])
    ev = q.on_end(9, "success")
    assert [(w, g.seq if g else None) for w, g in ev] == [
        ("reached", 2), ("current", 3), ("land", 3), ("reached", 3)]
    assert not q.running
    # A single goal replaces a running mission; the aborted episode is not ours any more.
    q.start(plan, first_seq=2)
    q.on_start(10, plan[2].position[:2])
    assert q.single((1.0, 2.0, 3.5)) == [("goal", Goal("goal", (1.0, 2.0, 3.5)))]
    assert not q.running and q.on_end(10, "aborted") == []
    q.on_start(11, (1.0, 2.0))
    assert q.on_end(11, "success") == [("reached", Goal("goal", (1.0, 2.0, 3.5)))]
    # A mission goal that fails stops the mission.
    q.start(plan, first_seq=1)
    q.on_start(12, plan[1].position[:2])
    assert [w for w, _ in q.on_end(12, "collision")] == ["failed:collision"]
    assert not q.running


# ---------------------------------------------------------------------------- MAVLink
@pytest.fixture
def flying(tmp_path: Path) -> Iterator[tuple[GcsRig, GoalService, list[Any]]]:
    """The rig's vehicle armed and holding 2.5 m up, with goals going to a list."""
    rig = GcsRig(tmp_path / "p.json")
    published: list[Any] = []
    svc = GoalService(rig.link, published.append)
    svc.install()
    yield rig, svc, published
    rig.close()


def command(rig: GcsRig, cmd: int, *params: float, ticks: int = 1) -> int:
    p = list(params) + [0.0] * (7 - len(params))
    (ack,) = of_type(rig.exchange(M.MAVLink_command_long_message(1, 1, cmd, 0, *p), ticks),
                     "COMMAND_ACK")
    return ack.result


def take_off(rig: GcsRig) -> None:
    assert command(rig, M.MAV_CMD_COMPONENT_ARM_DISARM, 1.0) == M.MAV_RESULT_ACCEPTED
    assert command(rig, M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, math.nan,
                   ticks=300) == M.MAV_RESULT_ACCEPTED
    assert str(rig.commander.state) == "HOLD" and not rig.commander.landed


def test_reposition_and_global_target_give_one_goal_bad_ones_denied(flying) -> None:
    rig, svc, published = flying
    lat, lon = lat_lon(13.0, -4.0)
    assert command(rig, M.MAV_CMD_DO_REPOSITION, -1, 0, 0, math.nan, lat, lon, math.nan) \
        == M.MAV_RESULT_DENIED  # on the ground
    assert svc.counters["goal.rejected.not_flying"] == 1 and published == []
    take_off(rig)
    z = rig.pos[2]
    # COMMAND_LONG: degrees (float32: ~0.5 m here), NaN altitude = where it flies now.
    assert command(rig, M.MAV_CMD_DO_REPOSITION, -1, 0, 0, math.nan, lat, lon, math.nan) \
        == M.MAV_RESULT_ACCEPTED
    assert published[-1] == pytest.approx((13.0, -4.0, z), abs=0.5)
    assert published[-1][2] == pytest.approx(z, abs=0.05)
    # COMMAND_INT, relative altitude: above home (3, 4, 0).
    got = rig.exchange(M.MAVLink_command_int_message(
        1, 1, REL, M.MAV_CMD_DO_REPOSITION, 0, 0, -1, 0, 0, math.nan, round(lat * 1e7),
        round(lon * 1e7), 3.0))
    assert of_type(got, "COMMAND_ACK")[0].result == M.MAV_RESULT_ACCEPTED
    assert published[-1] == pytest.approx((13.0, -4.0, 3.0), abs=0.05)
    assert any("Goal: flying to 13.0 -4.0" in t.text for t in of_type(got, "STATUSTEXT"))
    n = len(published)
    far_lat, far_lon = lat_lon(3.0, 80.0)  # 76 m from home, GF_MAX_HOR_DIST is 60 m
    for params in ((math.nan, lon, 3.0), (lat, math.nan, 3.0), (95.0, lon, 3.0),
                   (lat, 200.0, 3.0), (math.inf, lon, 3.0), (far_lat, far_lon, 3.0)):
        assert command(rig, M.MAV_CMD_DO_REPOSITION, -1, 0, 0, 0, *params) == \
            M.MAV_RESULT_DENIED, params
    got = rig.exchange(M.MAVLink_command_int_message(
        1, 1, REL, M.MAV_CMD_DO_REPOSITION, 0, 0, -1, 0, 0, 0, 2**31 - 1, 0, 3.0))
    assert of_type(got, "COMMAND_ACK")[0].result == M.MAV_RESULT_DENIED
    assert len(published) == n
    c = svc.counters
    assert (c["goal.rejected.bad_latitude"], c["goal.rejected.bad_longitude"],
            c["goal.rejected.beyond_geofence"]) == (4, 2, 1)
    # SET_POSITION_TARGET_GLOBAL_INT: x/y used, z ignored = keep the altitude.
    target = M.MAVLink_set_position_target_global_int_message(
        0, 1, 1, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0b0000_1111_1111_1100,
        round(lat * 1e7), round((lon + 1e-5) * 1e7), 0.0, 0, 0, 0, 0, 0, 0, 0, 0)
    rig.exchange(target)
    assert published[-1] == pytest.approx((13.76, -4.0, rig.pos[2]), abs=0.05)
    no_xy = M.MAVLink_set_position_target_global_int_message(
        0, 1, 1, M.MAV_FRAME_GLOBAL_INT, 0b0000_1111_1111_1011, 0, 0, 0.0, 0, 0, 0, 0, 0,
        0, 0, 0)
    rig.exchange(no_xy)
    assert svc.counters["goal.rejected.no_position"] == 1
    assert len(published) == n + 1 and svc.counters["goal.accepted"] == 3
    # Progress of a single goal: the sim's START toward it, then its END.
    x, y, z = published[-1]
    svc.on_episode(bm.episode_start(4, 0, (13.0, -4.0, z), (x, y, z), 0.0))
    rig.drain()
    svc.on_episode(bm.episode_end(4, "success", 30, 3.0))
    rig.tick()
    assert "Goal reached" in [t.text for t in of_type(rig.drain(), "STATUSTEXT")]


def test_mission_started_by_auto_mission_advances_on_success(flying) -> None:
    rig, svc, published = flying
    wps = [(12.0, 4.0), (12.0, 14.0)]
    items = [item(i, M.MAV_CMD_NAV_WAYPOINT, *lat_lon(x, y), 3.0) for i, (x, y) in
             enumerate(wps)]
    assert upload(rig, items, 0).type == M.MAV_MISSION_ACCEPTED
    assert command(rig, M.MAV_CMD_MISSION_START, 0, 0) == M.MAV_RESULT_DENIED  # on ground
    take_off(rig)
    home_z = rig.link.reporter.home[2]
    got = rig.exchange(M.MAVLink_command_long_message(1, 1, M.MAV_CMD_DO_SET_MODE, 0, 1, 4,
                                                      4, 0, 0, 0, 0))
    assert of_type(got, "COMMAND_ACK")[0].result == M.MAV_RESULT_ACCEPTED
    assert published == [pytest.approx((12.0, 4.0, home_z + 3.0), abs=0.05)]
    cur = of_type(got, "MISSION_CURRENT")
    assert (cur[-1].seq, cur[-1].mission_state) == (0, M.MISSION_STATE_ACTIVE)
    assert str(rig.commander.state) == "HOLD"  # the mode did not change: the policy flies

    def episode(ep: int, goal: Any, outcome: str) -> list[Any]:
        rig.drain()
        svc.on_episode(bm.episode_start(ep, 0, (0.0, 0.0, 0.0), goal, 0.0))
        svc.on_episode(bm.episode_end(ep, outcome, 20, 2.0))
        rig.tick()
        return rig.drain()

    got = episode(3, (50.0, 0.0, 3.5), "success")  # someone else's goal
    assert of_type(got, "MISSION_ITEM_REACHED") == [] and len(published) == 1
    got = episode(4, published[0], "success")
    assert [m.seq for m in of_type(got, "MISSION_ITEM_REACHED")] == [0]
    assert of_type(got, "MISSION_CURRENT")[0].seq == 1
    assert published[-1] == pytest.approx((12.0, 14.0, home_z + 3.0), abs=0.05)
    got = episode(5, published[1], "success")
    assert [m.seq for m in of_type(got, "MISSION_ITEM_REACHED")] == [1]
    assert "Mission complete" in [t.text for t in of_type(got, "STATUSTEXT")]
    assert svc.link.missions.state == M.MISSION_STATE_COMPLETE
    assert len(published) == 2 and svc.counters["mission.started"] == 1


def test_odd_values_are_answered_never_raise(flying) -> None:
    """NaN, inf and huge values in every parameter of the goal commands: each gets a
    COMMAND_ACK, no handler error, and only well-formed goals are published."""
    rig, svc, published = flying
    take_off(rig)
    odd = [math.nan, math.inf, -math.inf, 1e30, -1e30, 0.0, 47.4, 8.5, 4.0, 300.0, -1.0]
    rng = random.Random(5)
    for n in range(300):
        cmd = (M.MAV_CMD_DO_REPOSITION, M.MAV_CMD_MISSION_START, M.MAV_CMD_DO_SET_MODE)[n % 3]
        params = [rng.choice(odd) for _ in range(7)]
        got = rig.exchange(M.MAVLink_command_long_message(1, 1, cmd, 0, *params))
        assert [a.command for a in of_type(got, "COMMAND_ACK")] == [cmd], params
    for _ in range(100):
        x, y = rng.choice([0, 2**31 - 1, -(2**31), 473_977_420]), rng.choice([0, 85_455_940])
        rig.exchange(M.MAVLink_set_position_target_global_int_message(
            0, 1, 1, rng.choice([0, 3, 5, 6, 1, 11]), rng.randrange(0, 2**16), x, y,
            rng.choice(odd), 0, 0, 0, 0, 0, 0, 0, 0))
    assert rig.link.counters["handler_error"] == 0
    assert all(len(p) == 3 and all(math.isfinite(v) for v in p) for p in published)
