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
  step, else in HOLD. An episode that has flown OFFBOARD and leaves it (a failsafe such
  as setpoint loss, a ground station's mode change), or whose lockstep command for a step
  did not come within ``lockstep_timeout_s``, ends ``aborted`` at once, never merged
  with what follows; the node then flies control steps outside any episode (the
  failsafe goes on: HOLD, LAND) until OFFBOARD is asked for again, e.g. by a restarted
  policy (``skyloop up --restart on-failure``). Outcomes follow the env:
  collision is terminal; the goal is reached within ``goal_radius`` (2 m) at an
  altitude not above ``goal_max_altitude`` (6 m); ``max_steps`` (300) is a timeout.
* Free flight (``free_flight``, ``skyloop up --policy none``): the vehicle stays where
  it is, on the ground until a ground station flies it. An episode is one goal: it
  starts where the vehicle is, toward episode ``i``'s seeded goal, has no timeout, and
  ends at the goal (same rule) or at a collision (the vehicle is then put back on the
  ground at the next episode's start, disarmed). ``episodes`` 0: until stopped.
* Goals from the bus only (``goals_from_bus``, ``skyloop up --goals gcs``): free flight
  without seeded goals. Outside an episode (before the first goal, after each one) the
  node flies control steps as in the ground phase (publishing only the status and the
  estimated odometry, stamped with the standing stack time; the policy streams a hold
  in OFFBOARD, see ``policy/node.py``) until a goal comes;
  after a collision the vehicle is put on the ground where it fell, disarmed.
* A goal on ``skyloop/<vehicle>/goal`` (PoseStamped, world ENU) replaces the current
  one: the running episode ends as ``aborted`` and the next starts where the vehicle is,
  toward that goal (its START event carries it, which is how perception gets goals).
  A goal no episode could reach (not finite, below the terrain, inside an obstacle,
  above ``goal_max_altitude + goal_radius``) is refused: counted in ``goal_rejects``, a status
  event (STATUSTEXT at the bridge), nothing changes.

Per control step of an episode it publishes, in this order (one session, express off):
the step clock, the estimated odometry, the ground truth and the VLP-16 scan. Episode
START precedes step 0; END (outcome, steps) follows the last step, after the terminal
pose on ``truth``. **Stamps** are the stack time ``g * control_period``, ``g`` counting
episode steps over the run (integer nanoseconds, exact); the commander's own clock
counts every control step flown (ground phase included) and never goes backwards.

**Commands** (``cmd_vel``, ``VelocitySetpoint``, from the bridge): every one is offered
to the commander (:meth:`~sitl.commander.Commander.setpoint`; OFFBOARD needs a recent
one; an OFFBOARD request waits briefly for one on its way, see
:mod:`sitl.vehicle_service`). In OFFBOARD a body-frame yaw-rate setpoint (the policy's
action, ``bus.messages.is_action``) is flown with :meth:`EpisodeSim.step_body` (as the
env: rotated by the estimated yaw); otherwise the node flies the commander's world ENU output (HOLD,
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
from dataclasses import replace
from typing import Any

import numpy as np

from bus import keys
from bus import messages as m
from bus.task import TASK
from sitl.commander import State
from sitl.node_step import POLL_S, SimNodeConfig, StepLoop
from sitl.node_util import quat_from_matrix, quat_from_yaw

__all__ = ["EPISODE_LINE", "READY_LINE", "SUMMARY_LINE", "SimNode",
           "SimNodeConfig", "quat_from_matrix", "quat_from_yaw"]

log = logging.getLogger("skyloop.sim")
EPISODE_LINE = "SKYLOOP-EPISODE "
SUMMARY_LINE = "SKYLOOP-SUMMARY "
READY_LINE = "SKYLOOP-SIM-READY"


class SimNode(StepLoop):
    """Runs the vehicle and its episodes over a bus (see the module docstring)."""

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
        task = replace(TASK, max_steps=math.inf if c.free_flight else c.max_steps,
                       goal_radius=c.goal_radius, goal_max_altitude=c.goal_max_altitude)
        path = [s.vehicle.truth.position.copy()]
        flown = False  # the episode has flown OFFBOARD (seeded: it is placed in OFFBOARD)
        missed = self.missed
        self._missing = False  # a new episode waits the full lockstep timeout again
        while True:
            collided = self.tick(i)
            truth = s.vehicle.truth
            path.append(truth.position.copy())
            outcome = task.outcome(collided, s.goal_distance(), float(truth.position[2]),
                                   s.steps)
            offboard = self.commander.state == State.OFFBOARD
            broken = None if c.free_flight else \
                "the vehicle left OFFBOARD" if flown and not offboard else \
                "a step's command did not come" if self.missed > missed else None
            if outcome is None and (self._pending_goal is not None or self.stopping.is_set()
                                    or broken):
                outcome = "aborted"
                if broken:
                    self._rejoin_after = self.now()
                    # the step whose command did not come: its late answer means the
                    # policy is alive, only slow (a loaded machine), so flying goes on
                    self._late_stamp = (self.g - 1) * self.period_ns if missed != self.missed \
                        else None
                    log.warning("episode %d aborted at step %d: %s (%s)", i, s.steps, broken,
                                self.commander.state)
            flown = flown or offboard
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
        """The goal of episode ``i`` (None: a seeded, placed episode; with
        ``goals_from_bus``: stopping)."""
        if self._pending_goal is not None:
            goal, self._pending_goal = self._pending_goal, None
            return goal
        if self.config.goals_from_bus:
            if outcome == "collision":  # back on the ground where it fell
                self._place_on_ground(self.sim.vehicle.truth.position)
            return self.wait_goal()
        if not self.config.free_flight:
            if self._rejoin_after is not None:
                self.wait_rejoin(self._rejoin_after)
                self._rejoin_after = None
            return None
        start, goal = self.sim.world.sample_start_goal(
            np.random.default_rng(self.config.seed + i))
        if outcome == "collision":  # back on the ground at this episode's start
            self._place_on_ground(start)
        return goal

    def wait_rejoin(self, since: float) -> None:
        """Seeded episodes, after one aborted at commander time ``since`` because the
        vehicle left OFFBOARD or a lockstep command did not come: fly control steps
        outside any episode (failsafes, requests, status) until the vehicle is in
        OFFBOARD asked for after that, e.g. by a restarted policy node once it is ready
        to answer steps (a companion still starting may stream setpoints already), or,
        still in OFFBOARD, until the missed step's command comes late (the policy is
        alive, only slow); the next episode then starts placed as usual."""
        log.info("waiting for OFFBOARD to be asked for again before the next episode")
        cmdr = self.commander

        def late_answer() -> bool:
            return self._late_stamp is not None and self._last_cmd is not None and \
                m.nanoseconds(self._last_cmd.header.stamp) == self._late_stamp

        while not self.stopping.is_set() and not (
                cmdr.state == State.OFFBOARD and (cmdr.offboard_asked > since or late_answer())):
            if self.tick(None):
                self._place_on_ground(self.sim.vehicle.truth.position)

    def wait_goal(self) -> np.ndarray | None:
        """``goals_from_bus``: fly control steps outside any episode (the commander's
        output, or a hold the policy streams) until a goal comes; None if stopping."""
        while not self.stopping.is_set():
            if self._pending_goal is not None:
                goal, self._pending_goal = self._pending_goal, None
                return goal
            if self.tick(None):
                self._place_on_ground(self.sim.vehicle.truth.position)
            est = self.sim.vehicle.estimate  # telemetry for the bridge (stack time stands)
            self.pub[keys.ODOM].put(m.odometry(est.position, est.velocity,
                                               quat_from_yaw(est.yaw), self._stamp()))
        return None

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
            self.bus.declare_ready(c.vehicle, "sim")  # what the launcher waits on
            emit(READY_LINE)
        self.ground_phase(go)
        self.wait_subscribers()
        self.timing = dict.fromkeys(self.timing, 0.0)  # the episodes' share only
        t0 = time.monotonic()
        goal = s.goal.copy() if c.free_flight else None
        i = 0
        try:
            if c.goals_from_bus:
                goal = self.wait_goal()
            while (i < c.episodes or (c.free_flight and c.episodes <= 0)) \
                    and not self.stopping.is_set() and (goal is not None or not c.free_flight):
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
                   param_rejects=self.service.param_rejects, goal_rejects=self.goal_rejects,
                   **{k: round(v, 3) for k, v in self.timing.items()})
        if self.latencies_ms:
            lat = np.array(self.latencies_ms)
            out.update(latency_ms_p50=float(np.percentile(lat, 50)),
                       latency_ms_p99=float(np.percentile(lat, 99)),
                       latency_ms_max=float(lat.max()))
        emit(SUMMARY_LINE + json.dumps(out))
        return out
