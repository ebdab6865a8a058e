"""The simulator node (``skyloop sim``): :class:`~sitl.episode.EpisodeSim` on the bus.

It runs ``episodes`` seeded episodes of a scenario. Episode ``i`` is reset from
``numpy.random.default_rng(seed + i)``, exactly as ``UavNavEnv.reset(seed=seed + i)``
does, and the vehicle starts each episode airborne at the start point (as in the env).

Per control step ``k`` of an episode it publishes, in this order (one session, express
off, so subscribers see them in this order): the step clock (episode, step), the
estimated odometry, the ground truth and the VLP-16 scan (PointCloud2, BLOCK). Episode
START (seed, start, goal) precedes step 0; END (outcome, steps) follows the last step.
Outcomes follow the env's rules exactly: collision is terminal; the goal is reached
within ``goal_radius`` (2 m) with the altitude not above ``goal_max_altitude`` (6 m);
``max_steps`` (300) is a timeout.

**Stamps.** Every header stamp is the *stack time* ``g * control_period`` where ``g``
counts control steps over the whole run (monotonic across episodes; integer
nanoseconds, so exact). A command answers the step whose stamp it carries.

**Commands** (``cmd_vel``, TwistStamped): ``header.frame_id == "base_link"`` means
body-horizontal FLU (forward, left, up) + CCW yaw rate, applied like
:meth:`EpisodeSim.step_body` (rotated by the *estimated* yaw; what the policy's
MAV_FRAME_BODY_NED setpoints become); any other frame id is world ENU, applied like
:meth:`EpisodeSim.step_world` (what the commander flies in HOLD, LAND, ...).

**Clocks.** Lockstep (default): after publishing step ``k`` the node waits for the
command stamped ``k`` (older stamps are dropped and counted) and only then advances.
Real time: steps are paced by the wall clock at ``1 / control_period``; the node waits
for the command of step ``k`` until the step's deadline, applies it at once if it
arrives, else flies the newest command it has (a late command is a late command).
Latency (scan publish -> matching command back at the simulator) is measured in both.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bus import keys
from bus import messages as m
from bus.node import Bus
from sitl.episode import EpisodeConfig, EpisodeSim

log = logging.getLogger("skyloop.sim")
BODY_FRAME = "base_link"
EPISODE_LINE = "SKYLOOP-EPISODE "
SUMMARY_LINE = "SKYLOOP-SUMMARY "
READY_LINE = "SKYLOOP-SIM-READY"


@dataclass
class SimNodeConfig:
    """What the simulator node runs (env rules are the env's defaults)."""

    scenario: str = "valley"
    episodes: int = 1
    seed: int = 0
    vehicle: str = "uav1"
    realtime: bool = False
    max_steps: int = 300
    goal_radius: float = 2.0
    goal_max_altitude: float = 6.0
    match_timeout_s: float = 10.0  # wait for subscribers before the first episode
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)


def quat_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by ``yaw`` about z (ENU)."""
    return (0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw))


def quat_from_matrix(r: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a 3x3 rotation matrix (Shepperd's method)."""
    t = float(r[0, 0] + r[1, 1] + r[2, 2])
    if t > 0.0:
        s = 2.0 * math.sqrt(t + 1.0)
        return ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s,
                0.25 * s)
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2.0 * math.sqrt(max(1e-300, 1.0 + r[i, i] - r[j, j] - r[k, k]))
    q = [0.0, 0.0, 0.0, 0.0]
    q[i] = 0.25 * s
    q[j] = (r[j, i] + r[i, j]) / s
    q[k] = (r[k, i] + r[i, k]) / s
    q[3] = (r[k, j] - r[j, k]) / s
    return (q[0], q[1], q[2], q[3])


def outcome_of(collided: bool, distance: float, altitude: float, steps: int,
               cfg: SimNodeConfig) -> str | None:
    """The env's episode-end rules: ``success``/``collision``/``timeout`` or None."""
    if collided:
        return "collision"
    if distance <= cfg.goal_radius and altitude <= cfg.goal_max_altitude:
        return "success"
    if steps >= cfg.max_steps:
        return "timeout"
    return None


class SimNode:
    """Runs episodes over a :class:`Bus` (see the module docstring)."""

    def __init__(self, bus: Bus, config: SimNodeConfig) -> None:
        self.bus = bus
        self.config = c = config
        c.episode.scenario = c.scenario
        self.sim = EpisodeSim(c.episode)
        self.period_ns = round(self.sim.vehicle.config.control_period * 1e9)
        v = c.vehicle
        self.pub = {t: bus.publisher(t, v) for t in (keys.EPISODE, keys.CLOCK, keys.ODOM,
                                                      keys.TRUTH, keys.LIDAR_POINTS)}
        self.cmds = bus.inbox(keys.CMD_VEL, v, maxsize=256)
        self.g = 0  # control steps over the run
        self.stale = 0  # commands whose stamp was not the current step's
        self.late = 0  # real time: steps flown on an older command
        self.latencies_ms: list[float] = []
        self._last_cmd: Any = None
        self.results: list[dict] = []
        self.timing = {"publish_s": 0.0, "wait_s": 0.0, "step_s": 0.0}  # where wall time went

    # ------------------------------------------------------------------ publishing
    def _stamp(self) -> float:
        return self.g * self.period_ns / 1e9

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
    def _wait_command(self, t_pub: float, deadline: float | None) -> Any:
        """The command stamped with the current step (lockstep: wait for it; real time:
        until ``deadline``, then the newest command seen, or None)."""
        want = self.g * self.period_ns
        waited = 0.0
        while True:
            timeout = 5.0 if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                msg = self.cmds.get(timeout=timeout)
            except TimeoutError:
                if deadline is not None:
                    self.late += 1
                    return self._last_cmd
                waited += timeout
                log.warning("lockstep: no command for stack time %.1f s after %.0f s",
                            want / 1e9, waited)
                continue
            stamp = m.nanoseconds(msg.header.stamp)
            if stamp == want:
                self.latencies_ms.append((time.monotonic() - t_pub) * 1e3)
                self._last_cmd = msg
                return msg
            self.stale += 1
            if deadline is not None and stamp < want:
                self._last_cmd = msg

    def _apply(self, msg: Any) -> bool:
        if msg is None:
            return self.sim.step_world(np.zeros(4))
        cmd = np.array(m.twist_values(msg), dtype=np.float64)
        if msg.header.frame_id == BODY_FRAME:
            return self.sim.step_body(cmd)
        return self.sim.step_world(cmd)

    # ------------------------------------------------------------------ episodes
    def wait_subscribers(self) -> None:
        """Wait (bounded) until something listens to the scan, clock and episode topics."""
        for t in (keys.LIDAR_POINTS, keys.CLOCK, keys.EPISODE):
            if not self.pub[t].wait_matched(self.config.match_timeout_s):
                log.warning("no subscriber on %s after %.0f s; starting anyway",
                            self.pub[t].key, self.config.match_timeout_s)

    def run_episode(self, i: int) -> dict:
        c, s = self.config, self.sim
        seed = c.seed + i
        s.reset(np.random.default_rng(seed))
        self.pub[keys.EPISODE].put(m.episode_start(i, seed, s.start, s.goal, self._stamp(),
                                                   c.scenario))
        period = self.period_ns / 1e9
        next_tick = time.monotonic()
        path = [s.vehicle.truth.position.copy()]
        while True:
            if c.realtime:
                now = time.monotonic()
                if next_tick > now:
                    time.sleep(next_tick - now)
                next_tick = max(next_tick + period, time.monotonic() - period)
            t0 = time.perf_counter()
            t_pub = self._publish_step(i, s.steps)
            t1 = time.perf_counter()
            msg = self._wait_command(t_pub, next_tick if c.realtime else None)
            t2 = time.perf_counter()
            collided = self._apply(msg)
            self.timing["publish_s"] += t1 - t0
            self.timing["wait_s"] += t2 - t1
            self.timing["step_s"] += time.perf_counter() - t2
            self.g += 1
            truth = s.vehicle.truth
            path.append(truth.position.copy())
            outcome = outcome_of(collided, s.goal_distance(), float(truth.position[2]),
                                 s.steps, c)
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

    def run(self, emit: Any = print, go: Any = None) -> dict:
        """Run every episode; ``emit`` gets one JSON line per episode and the summary.
        With ``go`` (a callable that blocks), the node warms up, emits ``READY_LINE`` and
        waits for ``go()`` to return before the first episode (``skyloop up`` uses it to
        start the simulator while the policy is still connecting)."""
        self.sim.reset(np.random.default_rng(self.config.seed))  # warm up: the first scan
        self.sim.scan()  # compiles (numba); every episode's reset reseeds everything
        if go is not None:
            emit(READY_LINE)
            go()
        self.wait_subscribers()
        t0 = time.monotonic()
        for i in range(self.config.episodes):
            r = self.run_episode(i)
            self.results.append(r)
            emit(EPISODE_LINE + json.dumps(r))
        return self.summary(time.monotonic() - t0, emit)

    def summary(self, wall_s: float, emit: Any = print) -> dict:
        n = len(self.results)
        out: dict[str, Any] = {"episodes": n, "scenario": self.config.scenario,
                               "seed": self.config.seed,
                               "mode": "realtime" if self.config.realtime else "lockstep"}
        for o in ("success", "collision", "timeout"):
            out[o] = sum(r["outcome"] == o for r in self.results)
        steps = sum(r["steps"] for r in self.results)
        out.update(steps=steps, mean_steps=steps / n if n else 0.0, wall_s=wall_s,
                   steps_per_s=steps / wall_s if wall_s > 0 else 0.0,
                   stale_commands=self.stale, late_steps=self.late,
                   **{k: round(v, 3) for k, v in self.timing.items()})
        if self.latencies_ms:
            lat = np.array(self.latencies_ms)
            out.update(latency_ms_p50=float(np.percentile(lat, 50)),
                       latency_ms_p99=float(np.percentile(lat, 99)),
                       latency_ms_max=float(lat.max()))
        emit(SUMMARY_LINE + json.dumps(out))
        return out
