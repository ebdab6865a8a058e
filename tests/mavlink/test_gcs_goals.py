"""A ground station gives the trained policy its goals: ``skyloop up --goals gcs`` as real
processes on loopback (JSBSim, Zenoh, UDP MAVLink, the shipped policy).

The policy takes off and hovers in OFFBOARD. A pymavlink ground station sends bad
DO_REPOSITIONs (NaN and out-of-range latitude/longitude, beyond the geofence: each
DENIED, no goal on the bus), uploads a two-waypoint mission in the valley near the start
and starts it: MISSION_CURRENT goes 0 -> 1, MISSION_ITEM_REACHED 0 then 1 come with the
vehicle near each waypoint. Then a DO_REPOSITION (COMMAND_INT, as QGroundControl sends
it) flies the policy to a third point. The bus saw exactly those three goals.
"""

from __future__ import annotations

import contextlib
import math
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from loopback import free_port, interrupt, sigint_default, vehicle_messages

os.environ["MAVLINK20"] = "1"  # before mavutil is imported
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as M  # noqa: E402

from bus import keys  # noqa: E402
from bus import messages as bm  # noqa: E402
from bus.node import Bus  # noqa: E402
from bus.session import SessionConfig  # noqa: E402
from mavlink_bridge import frames  # noqa: E402
from mavlink_bridge.modes import encode_custom_mode  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
ORIGIN = (47.397742, 8.545594, 488.0)
OFFBOARD = encode_custom_mode(6, 0)
# Valley, seed 1000: the vehicle stands at (-10.3, -9.1); these are in free terrain.
WAYPOINTS = [(-0.35, -9.13), (-3.28, -2.06)]
REPOSITION = (-2.62, -11.2)
REACH_M = 3.0  # the sim's success is 2 m (truth); telemetry is the estimate, 10 Hz


def degE7(x: float, y: float) -> tuple[int, int]:
    lat, lon, _ = frames.enu_to_geodetic(x, y, 0.0, ORIGIN)
    return round(lat * 1e7), round(lon * 1e7)


class Gcs:
    """A pymavlink ground station that records what the vehicle says."""

    def __init__(self, port: int) -> None:
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255,
                                               source_component=190, dialect="common")
        self.mode: int | None = None
        self.pos: tuple[float, float, float] | None = None
        self.texts: list[str] = []
        self.acks: dict[int, int] = {}
        self.current: list[tuple[int, int]] = []  # MISSION_CURRENT (seq, state) changes
        self.reached: list[tuple[int, tuple[float, float, float]]] = []
        self.requests: list[int] = []
        self.mission_acks: list[int] = []

    def pump(self, seconds: float = 0.05) -> None:
        for msg in vehicle_messages(self.conn, seconds):
            kind = msg.get_type()
            if kind == "HEARTBEAT":
                self.mode = msg.custom_mode
            elif kind == "LOCAL_POSITION_NED":
                self.pos = frames.ned_to_enu(msg.x, msg.y, msg.z)
            elif kind == "STATUSTEXT":
                self.texts.append(msg.text)
            elif kind == "COMMAND_ACK":
                self.acks[msg.command] = msg.result
            elif kind == "MISSION_CURRENT":
                if not self.current or self.current[-1] != (msg.seq, msg.mission_state):
                    self.current.append((msg.seq, msg.mission_state))
            elif kind == "MISSION_ITEM_REACHED":
                assert self.pos is not None
                self.reached.append((msg.seq, self.pos))
            elif kind == "MISSION_REQUEST_INT":
                self.requests.append(msg.seq)
            elif kind == "MISSION_ACK":
                self.mission_acks.append(msg.type)

    def until(self, cond: Any, timeout: float, what: str) -> None:
        end = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > end:
                raise AssertionError(f"timed out waiting for {what}; heard {self.texts}")
            self.pump()

    def command_long(self, cmd: int, *params: float) -> int:
        self.acks.pop(cmd, None)
        self.conn.mav.command_long_send(1, 1, cmd, 0, *params)
        self.until(lambda: cmd in self.acks, 5.0, f"COMMAND_ACK {cmd}")
        return self.acks[cmd]

    def reposition_int(self, x: float, y: float, alt: float = math.nan,
                       xy: tuple[int, int] | None = None) -> int:
        lat, lon = xy or degE7(x, y)
        self.acks.pop(M.MAV_CMD_DO_REPOSITION, None)
        self.conn.mav.command_int_send(1, 1, M.MAV_FRAME_GLOBAL, M.MAV_CMD_DO_REPOSITION, 0, 0,
                                       -1, 1, 0, math.nan, lat, lon, alt)
        self.until(lambda: M.MAV_CMD_DO_REPOSITION in self.acks, 5.0, "reposition ACK")
        return self.acks[M.MAV_CMD_DO_REPOSITION]

    def upload(self, points: list[tuple[float, float]], alt: float) -> None:
        self.conn.mav.mission_count_send(1, 1, len(points), M.MAV_MISSION_TYPE_MISSION)
        answered: set[int] = set()
        while not self.mission_acks:
            self.until(lambda: self.mission_acks or set(self.requests) - answered, 5.0,
                       "MISSION_REQUEST_INT")
            for seq in sorted(set(self.requests) - answered):
                answered.add(seq)
                self.conn.mav.mission_item_int_send(
                    1, 1, seq, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_NAV_WAYPOINT, 0,
                    1, 0, 0, 0, math.nan, *degE7(*points[seq]), alt, M.MAV_MISSION_TYPE_MISSION)
        assert self.mission_acks == [M.MAV_MISSION_ACCEPTED]


@contextlib.contextmanager
def gcs_stack(tmp_path: Path, *args: str) -> Iterator[tuple[Gcs, list]]:
    """``skyloop up --goals gcs ARGS`` with a ground station on its GCS port; yields the
    station and the goals the bus carried."""
    udp = [free_port(socket.SOCK_DGRAM) for _ in range(4)]
    hub = f"tcp/127.0.0.1:{free_port()}"
    gcs = Gcs(udp[2])
    cmd = [sys.executable, "-m", "skyloop", "up", "--goals", "gcs", *args,
           "--hub", hub, "--api-port", str(udp[0]), "--api-local-port", str(udp[1]),
           "--gcs-port", str(udp[2]), "--gcs-local-port", str(udp[3])]
    env = dict(os.environ, XDG_STATE_HOME=str(tmp_path / "state"))
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, preexec_fn=sigint_default)
    bus = Bus.open(SessionConfig(hub=hub))
    goals: list[tuple[float, float, float]] = []
    bus.subscribe(keys.GOAL, "uav1", lambda msg: goals.append(tuple(bm.pose_values(msg)[0])))
    try:
        yield gcs, goals
    finally:
        out = interrupt(proc, timeout=20)
        print(out)
        bus.close()
        gcs.conn.close()


@pytest.fixture
def stack(tmp_path: Path):
    with gcs_stack(tmp_path, "--seed", "1000") as rig:
        yield rig


def test_mission_and_reposition_fly_the_policy_to_each_goal(stack) -> None:
    gcs, goals = stack
    gcs.until(lambda: gcs.mode == OFFBOARD and gcs.pos is not None, 120.0,
              "the policy in OFFBOARD, hovering")
    start = gcs.pos
    assert math.dist(start[:2], (-10.35, -9.13)) < 1.0 and start[2] > 1.5
    # Bad values: denied, nothing on the goal topic (the first goal seen is item 0's).
    far = degE7(start[0] + 80.0, start[1])  # GF_MAX_HOR_DIST: 60 m
    lat, lon = degE7(*WAYPOINTS[0])
    for xy in ((2**31 - 1, lon), (lat, 2**31 - 1), (950_000_000, lon), (lat, -1_900_000_000),
               far):
        assert gcs.reposition_int(0, 0, xy=xy) == M.MAV_RESULT_DENIED, xy
    assert gcs.command_long(M.MAV_CMD_DO_REPOSITION, -1, 0, 0, math.nan, math.nan, 8.5,
                            math.nan) == M.MAV_RESULT_DENIED
    assert sum("Reposition denied" in t for t in gcs.texts) == 6
    # The mission: two waypoints, altitude 0 = the flight level.
    gcs.upload(WAYPOINTS, 0.0)
    t0 = time.monotonic()
    assert gcs.command_long(M.MAV_CMD_MISSION_START, 0, 0, 0, 0, 0, 0, 0) == \
        M.MAV_RESULT_ACCEPTED
    gcs.until(lambda: len(gcs.reached) == 2, 90.0, "MISSION_ITEM_REACHED 0 and 1")
    mission_s = time.monotonic() - t0
    assert [seq for seq, _ in gcs.reached] == [0, 1]
    for (seq, pos), wp in zip(gcs.reached, WAYPOINTS, strict=True):
        print(f"item {seq}: reached at {math.dist(pos[:2], wp):.2f} m (horizontal), "
              f"altitude {pos[2]:.2f} m")
        assert math.dist(pos[:2], wp) < REACH_M
    gcs.until(lambda: gcs.current[-1][1] == M.MISSION_STATE_COMPLETE, 5.0, "mission complete")
    active = [seq for seq, state in gcs.current if state == M.MISSION_STATE_ACTIVE]
    assert active == [0, 1]
    assert "Mission complete" in gcs.texts
    # A click on the map: DO_REPOSITION as COMMAND_INT, altitude NaN = stay at this one.
    assert gcs.reposition_int(*REPOSITION) == M.MAV_RESULT_ACCEPTED
    t1 = time.monotonic()
    gcs.until(lambda: "Goal reached" in gcs.texts, 60.0, "Goal reached")
    reposition_s = time.monotonic() - t1
    gcs.pump(0.2)
    print(f"mission {mission_s:.1f} s, reposition {reposition_s:.1f} s, at "
          f"{math.dist(gcs.pos[:2], REPOSITION):.2f} m")
    assert math.dist(gcs.pos[:2], REPOSITION) < REACH_M
    assert gcs.mode == OFFBOARD  # hovering, waiting for the next goal
    assert len(goals) == 3
    for goal, xy in zip(goals, [*WAYPOINTS, REPOSITION], strict=True):
        assert math.dist(goal[:2], xy) < 0.05
    assert goals[0][2] == pytest.approx(3.5)  # SKY_FLIGHT_LVL above the datum


def flown_in_process(scenario: str, seeds: range) -> tuple[int, np.ndarray, np.ndarray]:
    """The first episode seed whose episode the default policy flies to its goal in the
    in-process env (deterministic), with that episode's start and goal: a goal the
    policy can reach in that world, so that what the stack test below checks is the
    plumbing (the drawn world, the ground station's goal, the policy's flight), not the
    policy's success rate."""
    from policy.training.evaluate import env_for, make_controller
    from policy.training.rollout import run_episode

    controller = make_controller(None)
    env = env_for(controller, scenario)
    try:
        for seed in seeds:
            result = run_episode(env, controller, seed)
            if result.outcome == "success":
                return seed, result.start, result.goal
    finally:
        env.close()
    raise AssertionError(f"the default policy reached no goal on {scenario}, seeds {seeds}")


def test_a_ground_station_gives_goals_in_a_drawn_city_world(tmp_path: Path) -> None:
    """``skyloop up --scenario family:city --goals gcs``: the sim draws a fresh city world
    from the seed (as the env does: the vehicle stands at the env's start), and a click on
    the map flies the default policy there through the streets."""
    seed, start, goal = flown_in_process("family:city", range(2000, 2020))
    with gcs_stack(tmp_path, "--scenario", "family:city", "--seed", str(seed)) as (gcs, goals):
        gcs.until(lambda: gcs.mode == OFFBOARD and gcs.pos is not None, 120.0,
                  "the policy in OFFBOARD, hovering")
        assert math.dist(gcs.pos[:2], start[:2]) < 1.0  # the same drawn world and start
        assert gcs.reposition_int(*goal[:2]) == M.MAV_RESULT_ACCEPTED
        t0 = time.monotonic()
        gcs.until(lambda: "Goal reached" in gcs.texts, 90.0, "Goal reached")
        gcs.pump(0.2)
        print(f"seed {seed}: {math.dist(start[:2], goal[:2]):.1f} m in "
              f"{time.monotonic() - t0:.1f} s, at {math.dist(gcs.pos[:2], goal[:2]):.2f} m")
        assert math.dist(gcs.pos[:2], goal[:2]) < REACH_M
        assert not any(t.startswith("Mission stopped") for t in gcs.texts), gcs.texts
        assert len(goals) == 1 and math.dist(goals[0][:2], goal[:2]) < 0.05
