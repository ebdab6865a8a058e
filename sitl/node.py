"""The simulator node (``skyloop sim``): the vehicle -- :class:`~sitl.episode.EpisodeSim`,
its commander and failsafes -- on the bus.

**The commander lives here** (issue 5): :class:`~sitl.commander.Commander` is stepped
every control step with the vehicle's state and decides what the autopilot flies, so its
failsafes act whatever happens to the bridge or the policy process. Requests (arm,
takeoff, modes, ...), the status topic and parameters: :mod:`sitl.vehicle_service`.

**Phases.** At start the vehicle stands on the ground, disarmed, at episode 0's start
point (``--seed``); the node runs wall-clock-paced control steps (only ``status`` is
published; stamps are 0: the stack clock has not started) and serves requests, so a
client can arm and take off under JSBSim. The episodes begin at "go" (``--wait-go``: a
stdin line from ``skyloop up``; without it, once the commander is in OFFBOARD); while
the commander is in OFFBOARD before go, the node waits (nothing answers steps yet).

* Seeded episodes (default): episode ``i`` is reset from
  ``numpy.random.default_rng(seed + i)`` exactly as ``UavNavEnv.reset(seed=seed + i)``
  does and the vehicle is placed airborne at its start (as in the env); the commander
  is placed with it (:meth:`~sitl.commander.Commander.place`: home there, collision latch
  cleared) and continues in OFFBOARD if it flew OFFBOARD in the previous episode's last
  step, else in HOLD. Outcomes follow the env: collision is terminal; the goal is
  reached within ``goal_radius`` (2 m) at an altitude not above ``goal_max_altitude``
  (6 m); ``max_steps`` (300) is a timeout.
* Free flight (``free_flight``, ``skyloop up --policy none``): the vehicle stays where
  it is, on the ground until a ground station flies it. An episode is one goal: it
  starts where the vehicle is, toward episode ``i``'s seeded goal, has no timeout, and
  ends at the goal (same rule) or at a collision (the vehicle is then put back on the
  ground at the next episode's start, disarmed). ``episodes`` 0: until stopped.
* A goal on ``skyloop/<vehicle>/goal`` (PoseStamped, world ENU) replaces the current
  one: the running episode ends as ``aborted`` and the next starts where the vehicle is,
  toward that goal (its START event carries it, which is how perception gets goals).

Per control step of an episode it publishes, in this order (one session, express off):
the step clock, the estimated odometry, the ground truth and the VLP-16 scan. Episode
START precedes step 0; END (outcome, steps) follows the last step, after the terminal
pose on ``truth``. **Stamps** are the stack time ``g * control_period``, ``g`` counting
episode steps over the run (integer nanoseconds, exact); the commander's own clock
counts every control step flown (ground phase included) and never goes backwards.

**Commands** (``cmd_vel``, TwistStamped, from the bridge): every one is offered to the
commander (:meth:`~sitl.commander.Commander.setpoint`; the stream OFFBOARD needs).
``frame_id`` ``"base_link"``: body-horizontal FLU + CCW yaw rate; ``"world"``: ENU; a
``"|yaw"`` suffix: ``angular.z`` is an absolute ENU heading target. In OFFBOARD a
``base_link`` command is flown with :meth:`EpisodeSim.step_body` (as the env: rotated by
the estimated yaw); otherwise the node flies the commander's world ENU output (HOLD,
LAND, RTL, TAKEOFF; motors stopped while disarmed or idle on the ground). Outside
OFFBOARD flight of a seeded episode (env rules there: any terrain contact is a
collision), the JSBSim ground follows the terrain under the vehicle so it can land, and
touching the terrain gently (|vz| <= 1 m/s) is a touchdown, not a collision.

**Clocks.** Lockstep (default) gates only in OFFBOARD during an episode: after
publishing step ``k`` the node waits for the command stamped ``k`` (others are offered
to the commander and counted stale). If none comes within ``lockstep_timeout_s`` of wall
time (the policy or the bridge died) the step is flown without it (the last setpoint,
as PX4) and counted in ``missed``; until a command matches again each further step
waits one control period only, so the commander's setpoint-loss failsafe acts within
seconds. Outside OFFBOARD nobody answers steps, so steps are paced by the wall clock
(a ground station sees takeoff, hold, landing and RTL in real time). Real time: every
step is wall-paced; in OFFBOARD the node waits for the command of step ``k`` until the
step's deadline, else flies the newest one. Latency (scan publish -> matching command
back) is measured in both.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bus import keys
from bus import messages as m
from bus.node import Bus
from sitl.commander import Commander, State, VehicleSample
from sitl.episode import EpisodeConfig, EpisodeSim
from sitl.flight_model import REST_HEIGHT
from sitl.node_util import outcome_of, quat_from_matrix, quat_from_yaw
from sitl.vehicle_service import VehicleService

__all__ = ["BODY_FRAME", "EPISODE_LINE", "READY_LINE", "SUMMARY_LINE", "SimNode",
           "SimNodeConfig", "outcome_of", "quat_from_matrix", "quat_from_yaw"]

log = logging.getLogger("skyloop.sim")
BODY_FRAME = "base_link"
YAW_SUFFIX = "|yaw"
EPISODE_LINE = "SKYLOOP-EPISODE "
SUMMARY_LINE = "SKYLOOP-SUMMARY "
READY_LINE = "SKYLOOP-SIM-READY"
TOUCHDOWN_SPEED = 1.0  # m/s, a gentler terrain contact outside OFFBOARD is a landing
POLL_S = 0.01  # s, how often requests are served while the node waits


@dataclass
class SimNodeConfig:
    """What the simulator node runs (env rules are the env's defaults)."""

    scenario: str = "valley"
    episodes: int = 1  # free flight: 0 = until stopped
    seed: int = 0
    vehicle: str = "uav1"
    realtime: bool = False
    max_steps: int = 300
    goal_radius: float = 2.0
    goal_max_altitude: float = 6.0
    match_timeout_s: float = 10.0  # wait for subscribers before the first episode
    free_flight: bool = False
    lockstep_timeout_s: float = 2.0
    params: dict[str, float] = field(default_factory=dict)  # bus.params names
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)


class SimNode:
    """Runs the vehicle and its episodes over a :class:`Bus` (see the module docstring)."""

    def __init__(self, bus: Bus, config: SimNodeConfig) -> None:
        self.bus = bus
        self.config = c = config
        c.episode.scenario = c.scenario
        self.sim = EpisodeSim(c.episode)
        self.period_ns = round(self.sim.vehicle.config.control_period * 1e9)
        self.period = self.period_ns / 1e9
        v = c.vehicle
        self.pub = {t: bus.publisher(t, v) for t in (keys.EPISODE, keys.CLOCK, keys.ODOM,
                                                      keys.TRUTH, keys.LIDAR_POINTS)}
        self.cmds = bus.inbox(keys.CMD_VEL, v, maxsize=256)
        self.goals = bus.inbox(keys.GOAL, v, maxsize=16)
        self.commander = Commander()
        self.service = VehicleService(bus, v, self.commander, self.sim.vehicle)
        for name, value in c.params.items():
            if not self.service.set_param(name, value):
                raise ValueError(f"bad parameter {name}={value!r} (see bus/params.py)")
        self.g = 0  # episode control steps over the run (stamps)
        self.vsteps = 0  # every control step flown (the commander's clock)
        self.stale = 0  # commands whose stamp was not the current step's
        self.late = 0  # real time: steps flown on an older command
        self.missed = 0  # lockstep: OFFBOARD steps flown without their command
        self.latencies_ms: list[float] = []
        self._missing = False
        self._last_cmd: Any = None
        self._next_tick: float | None = None
        self._pending_goal: np.ndarray | None = None
        self._resume = State.HOLD  # the mode a placed episode continues in
        self.results: list[dict] = []
        self.stopping = threading.Event()  # set: end the episode (aborted) and the run
        self.timing = {"publish_s": 0.0, "wait_s": 0.0, "step_s": 0.0}  # where wall time went

    # ------------------------------------------------------------------ clocks
    def _stamp(self) -> float:
        return self.g * self.period_ns / 1e9

    def now(self) -> float:
        """The commander's clock: control steps flown since start, in seconds."""
        return self.vsteps * self.period_ns / 1e9

    def _serve_until(self, deadline: float) -> None:
        """Serve requests (and take commands) until the wall-clock ``deadline``."""
        while True:
            self._drain_commands()
            self.service.serve(self.now())
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            time.sleep(min(POLL_S, remaining))

    def _pace(self) -> float:
        """Wait for this step's wall-clock tick; return the step's deadline."""
        if self._next_tick is None:
            self._next_tick = time.monotonic()
        self._serve_until(self._next_tick)
        self._next_tick = max(self._next_tick + self.period, time.monotonic() - self.period)
        return self._next_tick

    # ------------------------------------------------------------------ publishing
    def _publish_step(self, episode: int, step: int) -> float:
        """Publish clock, odometry, truth and scan of the current state; return the wall
        time of the scan publish."""
        s, stamp = self.sim, self._stamp()
        est, truth = s.vehicle.estimate, s.vehicle.truth
        self.pub[keys.CLOCK].put(m.step_clock(step, stamp, episode))
        self.pub[keys.ODOM].put(m.odometry(est.position, est.velocity, quat_from_yaw(est.yaw),
                                           stamp))
        self.pub[keys.TRUTH].put(m.odometry(truth.position, truth.velocity,
                                            quat_from_matrix(truth.rotation), stamp))
        cloud = m.pointcloud(s.scan(), stamp)
        t_pub = time.monotonic()
        self.pub[keys.LIDAR_POINTS].put(cloud)
        return t_pub

    # ------------------------------------------------------------------ commands
    def _offer(self, msg: Any) -> None:
        """Offer a ``cmd_vel`` to the commander (see the module docstring's frames)."""
        vx, vy, vz, wz = m.twist_values(msg)
        frame = msg.header.frame_id
        heading = frame.endswith(YAW_SUFFIX)
        self.commander.setpoint(self.now(), vx, vy, vz, 0.0 if heading else wz,
                                body=frame.startswith(BODY_FRAME),
                                yaw=wz if heading else None)

    def _drain_commands(self) -> None:
        while (msg := self.cmds.get_nowait()) is not None:
            self._offer(msg)
            self._last_cmd = msg

    def _wait_command(self, t_pub: float, deadline: float | None) -> Any:
        """The command stamped with the current step. Lockstep (``deadline`` None): wait
        for it (see the module docstring for the timeout), None if it did not come;
        real time: until ``deadline``, then the newest command seen."""
        want = self.g * self.period_ns
        if deadline is None:
            wait = self.period if self._missing else self.config.lockstep_timeout_s
            give_up = time.monotonic() + wait
        while True:
            end = give_up if deadline is None else deadline
            remaining = end - time.monotonic()
            if remaining <= 0:
                if deadline is not None:
                    self.late += 1
                    return self._last_cmd
                self.missed += 1
                if not self._missing:
                    log.warning("lockstep: no command for stack time %.1f s within %.1f s "
                                "(wall); stepping without it", want / 1e9, wait)
                self._missing = True
                return None
            try:
                msg = self.cmds.get(timeout=min(POLL_S, remaining))
            except TimeoutError:
                self.service.serve(self.now())
                if self.commander.state != State.OFFBOARD:  # a request changed the mode
                    return None
                continue
            self._offer(msg)
            stamp = m.nanoseconds(msg.header.stamp)
            if stamp == want:
                self.latencies_ms.append((time.monotonic() - t_pub) * 1e3)
                self._last_cmd, self._missing = msg, False
                return msg
            self.stale += 1
            if deadline is not None and stamp < want:
                self._last_cmd = msg

    # ------------------------------------------------------------------ one step
    def _sample(self) -> VehicleSample:
        s = self.sim
        est, truth = s.vehicle.estimate, s.vehicle.truth
        x, y, z = (float(v) for v in truth.position)
        agl = z - float(s.world.terrain_height(x, y)) - REST_HEIGHT
        return VehicleSample(float(est.position[2]), float(est.velocity[2]), est.yaw, agl,
                             float(est.position[0]), float(est.position[1]))

    def _touchdown(self) -> bool:
        """A gentle terrain contact with nothing else touched (see the module doc)."""
        s = self.sim
        truth = s.vehicle.truth
        if abs(float(truth.velocity[2])) > TOUCHDOWN_SPEED:
            return False
        return not s.world.collides_off_terrain(truth.position, s.config.body_radius, s.time)

    def tick(self, episode: int | None) -> bool:
        """One control period (``episode`` None: the ground phase, nothing published but
        the status); returns whether the vehicle collided."""
        c, s, cmdr = self.config, self.sim, self.commander
        offboard = cmdr.state == State.OFFBOARD
        gated = episode is not None and offboard and not c.realtime
        t0 = time.perf_counter()
        deadline = None
        if gated:
            self._next_tick = None
        else:
            deadline = self._pace()
        t1 = t_pubbed = time.perf_counter()
        msg = None
        if episode is not None:
            t_pub = self._publish_step(episode, s.steps)
            t_pubbed = time.perf_counter()
            if offboard:
                msg = self._wait_command(t_pub, deadline)
        if not (episode is not None and offboard):
            self._drain_commands()
        t2 = time.perf_counter()
        now = self.now()
        self.service.serve(now)
        if (goal := self.goals.get_nowait()) is not None:
            while (newer := self.goals.get_nowait()) is not None:
                goal = newer
            self._pending_goal = m.pose_values(goal)[0]
        out = cmdr.step(now, self._sample())
        env_rules = episode is not None and not c.free_flight and cmdr.state == State.OFFBOARD
        if not env_rules:
            x, y = s.vehicle.truth.position[:2]
            s.vehicle.set_ground(float(s.world.terrain_height(x, y)))
        if cmdr.state == State.OFFBOARD and msg is not None and \
                msg.header.frame_id == BODY_FRAME:
            collided = s.step_body(np.array(m.twist_values(msg), dtype=np.float64))
        else:
            motors = cmdr.armed and cmdr.state != State.ARMED
            collided = s.step_world(np.array(out, dtype=np.float64), motors)
        self.vsteps += 1
        if episode is not None:
            self.g += 1
        if collided and not env_rules and self._touchdown():
            collided = False
        self._resume = cmdr.state  # the mode the next placed episode continues in
        if collided:
            cmdr.collision(self.now())
        self.service.publish_status(self._stamp(), self.now())
        self.timing["publish_s"] += t_pubbed - t1
        self.timing["wait_s"] += (t1 - t0) + (t2 - t_pubbed)
        self.timing["step_s"] += time.perf_counter() - t2
        return collided

    # ------------------------------------------------------------------ episodes
    def wait_subscribers(self) -> None:
        """Wait (bounded) until something listens to the scan, clock and episode topics."""
        for t in (keys.LIDAR_POINTS, keys.CLOCK, keys.EPISODE):
            if not self.pub[t].wait_matched(self.config.match_timeout_s):
                log.warning("no subscriber on %s after %.0f s; starting anyway",
                            self.pub[t].key, self.config.match_timeout_s)

    def run_episode(self, i: int, goal: np.ndarray | None = None) -> dict:
        """Episode ``i``: seeded and placed airborne, or (``goal`` given) from where the
        vehicle is toward ``goal``."""
        c, s = self.config, self.sim
        seed = c.seed + i
        if goal is None:
            s.reset(np.random.default_rng(seed))
            self.commander.place(self.now(), airborne=True, mode=self._resume)
        else:
            s.new_goal(goal)
        self.pub[keys.EPISODE].put(m.episode_start(i, seed, s.start, s.goal, self._stamp(),
                                                   c.scenario))
        max_steps = math.inf if c.free_flight else c.max_steps
        path = [s.vehicle.truth.position.copy()]
        while True:
            collided = self.tick(i)
            truth = s.vehicle.truth
            path.append(truth.position.copy())
            outcome = outcome_of(collided, s.goal_distance(), float(truth.position[2]),
                                 s.steps, c.goal_radius, c.goal_max_altitude, max_steps)
            if outcome is None and (self._pending_goal is not None or self.stopping.is_set()):
                outcome = "aborted"
            if outcome is not None:
                break
        # The terminal pose, for logs (training from logs needs it; only the recorder
        # listens to truth, so the lockstep chain is untouched).
        self.pub[keys.TRUTH].put(m.odometry(truth.position, truth.velocity,
                                            quat_from_matrix(truth.rotation), self._stamp()))
        self.pub[keys.EPISODE].put(m.episode_end(i, outcome, s.steps, self._stamp(), seed,
                                                 c.scenario))
        length = float(np.sum(np.linalg.norm(np.diff(np.array(path), axis=0), axis=1)))
        return {"episode": i, "seed": seed, "outcome": outcome, "steps": s.steps,
                "path_length": length}

    def _next_goal(self, i: int, outcome: str) -> np.ndarray | None:
        """The goal of episode ``i`` (None: a seeded, placed episode)."""
        if self._pending_goal is not None:
            goal, self._pending_goal = self._pending_goal, None
            return goal
        if not self.config.free_flight:
            return None
        start, goal = self.sim.world.sample_start_goal(
            np.random.default_rng(self.config.seed + i))
        if outcome == "collision":  # back on the ground at this episode's start
            self._place_on_ground(start)
        return goal

    def _place_on_ground(self, start: np.ndarray) -> None:
        self.sim.place_on_ground(float(start[0]), float(start[1]), self.sim.vehicle.estimate.yaw)
        self.commander.place(self.now(), airborne=False)

    def ground_phase(self, go: Callable[[], Any] | None) -> None:
        """Until "go" (see the module docstring): on the ground, serving requests."""
        started = threading.Event()
        if go is not None:
            threading.Thread(target=lambda: (go(), started.set()), daemon=True).start()
        while not (started.is_set() or self.stopping.is_set()):
            if go is None and (self.config.free_flight
                               or self.commander.state == State.OFFBOARD):
                return
            if self.commander.state == State.OFFBOARD:  # nothing answers steps yet
                self._next_tick = None
                self._serve_until(time.monotonic() + POLL_S)
                self.service.publish_status(self._stamp(), self.now())
                continue
            if self.tick(None):
                self._place_on_ground(self.sim.vehicle.truth.position)
        self._resume = self.commander.state

    def run(self, emit: Any = print, go: Any = None) -> dict:
        """Run every episode; ``emit`` gets one JSON line per episode and the summary.
        With ``go`` (a callable that blocks), the node warms up, emits ``READY_LINE`` and
        flies the ground phase until ``go()`` returns (``skyloop up`` uses it)."""
        c, s = self.config, self.sim
        s.reset(np.random.default_rng(c.seed))  # warm up: the first scan compiles (numba)
        s.scan()
        self._place_on_ground(s.start)  # episode 0's start; its goal is free flight's
        self.service.publish_status(self._stamp(), self.now(), force=True)
        if go is not None:
            emit(READY_LINE)
        self.ground_phase(go)
        self.wait_subscribers()
        self.timing = dict.fromkeys(self.timing, 0.0)  # the episodes' share only
        t0 = time.monotonic()
        goal = s.goal.copy() if c.free_flight else None
        i = 0
        try:
            while (i < c.episodes or (c.free_flight and c.episodes <= 0)) \
                    and not self.stopping.is_set():
                r = self.run_episode(i, goal)
                self.results.append(r)
                emit(EPISODE_LINE + json.dumps(r))
                i += 1
                goal = self._next_goal(i, r["outcome"])
        except KeyboardInterrupt:
            if not c.free_flight:
                raise
            log.info("stopped after %d episodes", len(self.results))
        return self.summary(time.monotonic() - t0, emit)

    def summary(self, wall_s: float, emit: Any = print) -> dict:
        n = len(self.results)
        out: dict[str, Any] = {"episodes": n, "scenario": self.config.scenario,
                               "seed": self.config.seed,
                               "mode": "realtime" if self.config.realtime else "lockstep"}
        for o in ("success", "collision", "timeout", "aborted"):
            out[o] = sum(r["outcome"] == o for r in self.results)
        steps = sum(r["steps"] for r in self.results)
        out.update(steps=steps, mean_steps=steps / n if n else 0.0, wall_s=wall_s,
                   steps_per_s=steps / wall_s if wall_s > 0 else 0.0,
                   stale_commands=self.stale, late_steps=self.late, missed_steps=self.missed,
                   param_rejects=self.service.param_rejects,
                   **{k: round(v, 3) for k, v in self.timing.items()})
        if self.latencies_ms:
            lat = np.array(self.latencies_ms)
            out.update(latency_ms_p50=float(np.percentile(lat, 50)),
                       latency_ms_p99=float(np.percentile(lat, 99)),
                       latency_ms_max=float(lat.max()))
        emit(SUMMARY_LINE + json.dumps(out))
        return out
