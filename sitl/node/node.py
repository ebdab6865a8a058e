"""The simulator node (``skyloop sim``): the vehicle -- :class:`~sitl.episode.EpisodeSim`,
its commander and failsafes -- on the bus.

**The commander lives here** (issue 5): :class:`~sitl.commander.machine.Commander` is stepped
every control step with the vehicle's state and decides what the autopilot flies, so its
failsafes act whatever happens to the bridge or the policy process. Requests (arm,
takeoff, modes, ...), the status topic and parameters: :mod:`sitl.node.vehicle_service`.

**Phases.** At start the vehicle stands on the ground, disarmed, at episode 0's start
point (``--seed``); the node runs wall-clock-paced control steps (only ``status`` is
published; stamps are 0: the stack clock has not started) and serves requests, so a
client can arm and take off under JSBSim. The episodes begin at "go" (``--wait-go``: a
stdin line from ``skyloop up``; without it, once the commander is in OFFBOARD); while
the commander is in OFFBOARD before go, the node waits (nothing answers steps yet).

* Seeded episodes (default): episode ``i`` is reset from
  ``numpy.random.default_rng(seed + i)`` exactly as ``UavNavEnv.reset(seed=seed + i)``
  does and the vehicle is placed airborne at its start (as in the env); the commander
  is placed with it (:meth:`~sitl.commander.machine.Commander.place`: home there, collision latch
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
  in OFFBOARD, see ``policy/nodes/node.py``) until a goal comes;
  after a collision the vehicle is put on the ground where it fell, disarmed.
* A goal on ``skyloop/<vehicle>/goal`` (PoseStamped, world ENU) replaces the current
  one: the running episode ends as ``aborted`` and the next starts where the vehicle is,
  toward that goal (its START event carries it, which is how perception gets goals).
  A goal no episode could reach (not finite, below the terrain, inside an obstacle,
  above ``goal_max_altitude + goal_radius``) is refused: counted in ``goal_rejects``, a status
  event (STATUSTEXT at the bridge), nothing changes.

Per control step of an episode it publishes, in this order (one session, express off):
the step clock, the estimated odometry, the ground truth and the VLP-16 scan; after the
step is flown, its record (``step_record``: :meth:`EpisodeSim.record`, the one source of
the outcome here as in the env; stamped with the next step's time). Episode START
precedes step 0; END (outcome, steps) follows the last step's record, after the terminal
pose on ``truth``. **Stamps** are the stack time ``g * control_period``, ``g`` counting
episode steps over the run (integer nanoseconds, exact); the commander's own clock
counts every control step flown (ground phase included) and never goes backwards.

**Commands** (``cmd_vel``, ``VelocitySetpoint``, from the bridge): every one is offered
to the commander (:meth:`~sitl.commander.machine.Commander.setpoint`; OFFBOARD needs a recent
one; an OFFBOARD request waits briefly for one on its way, see
:mod:`sitl.node.vehicle_service`). In OFFBOARD a body-frame yaw-rate setpoint (the policy's
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

**Parts** (composed, no inheritance): :class:`SimNode` builds them and runs the node
(warm-up, readiness, the ground phase, the episodes, the summary).
:class:`~sitl.node.pacing.StackClock` (stamps and the commander's clock),
:class:`~sitl.node.pacing.Pacer` (wall-clock pacing), :class:`~sitl.node.pacing.CommandGate`
(which command answers which step, the lockstep timeout, stale/late/missed counts),
:class:`~sitl.node.pacing.Rejoin` (what is kept after lockstep broke, to join the policy
again), :class:`~sitl.node.step.GoalIntake` (goals from the bus),
:class:`~sitl.node.step.ControlStep` (one control period) and
:class:`~sitl.node.episodes.EpisodeRunner` (the phases above). The caller's
:class:`SimNodeConfig` is never changed: the node runs on
:meth:`SimNodeConfig.resolved`'s copy.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Any

import numpy as np

from bus import keys
from bus.node import Bus, inbox_drops
from sitl.commander.machine import Commander
from sitl.episode import EpisodeSim
from sitl.node.episodes import EpisodeRunner
from sitl.node.pacing import CommandGate, Pacer, Rejoin, StackClock
from sitl.node.step import ControlStep, GoalIntake, SimNodeConfig
from sitl.node.util import quat_from_matrix, quat_from_yaw
from sitl.node.vehicle_service import VehicleService

__all__ = ["EPISODE_LINE", "READY_LINE", "SUMMARY_LINE", "SimNode",
           "SimNodeConfig", "quat_from_matrix", "quat_from_yaw"]

log = logging.getLogger("skyloop.sim")
EPISODE_LINE = "SKYLOOP-EPISODE "
SUMMARY_LINE = "SKYLOOP-SUMMARY "
READY_LINE = "SKYLOOP-SIM-READY"


class SimNode:
    """Runs the vehicle and its episodes over a bus (see the module docstring)."""

    def __init__(self, bus: Bus, config: SimNodeConfig) -> None:
        self.bus = bus
        if (config.free_flight or config.goals_from_bus) and not config.realtime:
            log.info("free flight runs in real time")  # nothing answers steps for a GCS
        self.config = c = config.resolved()
        self.sim = EpisodeSim(c.episode)
        self.clock = StackClock(round(self.sim.vehicle.config.control_period * 1e9))
        v = c.vehicle
        pub = {t: bus.publisher(t, v) for t in (keys.EPISODE, keys.CLOCK, keys.ODOM,
                                                 keys.TRUTH, keys.LIDAR_POINTS,
                                                 keys.STEP_RECORD)}
        self.pub = pub
        self.cmds = bus.inbox(keys.CMD_VEL, v, maxsize=256)
        goal_inbox = bus.inbox(keys.GOAL, v, maxsize=16)
        self.commander = Commander()
        self.service = VehicleService(bus, v, self.commander, self.sim.vehicle,
                                      sensor=self.sim)
        self.rejoin = Rejoin()
        self.gate = CommandGate(self.cmds, self.commander, self.clock, self.rejoin,
                                c.lockstep_timeout_s, serve=self._serve_requests)
        self.service.take_setpoints = self.gate.take
        for name, value in c.params.items():
            if not self.service.set_param(name, value):
                raise ValueError(f"bad parameter {name}={value!r} (see bus/params.py)")
        if c.free_flight and not self.sim.source.fixed:
            # a family in free flight: one world of it never drawn in training
            from sitl.world.families import eval_worlds

            self.sim.use_world(eval_worlds(self.sim.source.families[0], 1)[0])
            log.info("free flight in %s (a held-out world of the family)",
                     self.sim.world_name)
        area = self.sim.world.scenario.area
        fence = self.commander.config.geofence
        if fence > 0 and (area.size_x**2 + area.size_y**2) ** 0.5 > fence:
            log.warning("scenario %s spans more than GF_MAX_HOR_DIST = %g m: a long flight "
                        "may end in a geofence RTL (the env has no geofence)", c.scenario,
                        fence)
        self.pacer = Pacer(self.clock.period, self._serve)
        self.goals = GoalIntake(goal_inbox, c, self.sim, self.service)
        self.step = ControlStep(c, self.sim, self.commander, self.service, self.clock,
                                self.pacer, self.gate, self.goals, pub)
        self.stopping = threading.Event()  # set: end the episode (aborted) and the run
        self.episodes = EpisodeRunner(c, self.step, self.rejoin, self.stopping)
        self.results: list[dict] = []

    def now(self) -> float:
        """The commander's clock: control steps flown since start, in seconds."""
        return self.clock.now()

    @property
    def goal_rejects(self) -> int:
        """Goals from the bus no episode could reach."""
        return self.goals.rejects

    def counters(self) -> dict[str, int]:
        """What the node's bounded inboxes dropped (the oldest item, when one is full),
        per inbox (``dropped_<topic>``) and in total (``dropped``): the counters line
        ``skyloop sim`` prints last. Read at exit; the inboxes count as they drop, so
        the control step pays nothing for it."""
        return inbox_drops((self.cmds, self.goals.inbox, self.service.params))

    def _serve_requests(self) -> None:
        """Requests, and the status (on changes, and as a keepalive)."""
        now = self.clock.now()
        self.service.serve(now)
        self.service.publish_status(self.clock.stamp(), now)

    def _serve(self) -> None:
        """What the node does while it waits for a paced tick: commands, requests, status."""
        self.gate.drain()
        self._serve_requests()

    def wait_subscribers(self) -> None:
        """Wait (bounded) until something listens to the scan, clock and episode topics."""
        for t in (keys.LIDAR_POINTS, keys.CLOCK, keys.EPISODE):
            if not self.pub[t].wait_matched(self.config.match_timeout_s):
                log.warning("no subscriber on %s after %.0f s; starting anyway",
                            self.pub[t].key, self.config.match_timeout_s)

    def run(self, emit: Any = print, go: Any = None) -> dict:
        """Run every episode; ``emit`` gets one JSON line per episode and the summary.
        With ``go`` (a callable that blocks), the node warms up, emits ``READY_LINE`` and
        flies the ground phase until ``go()`` returns (``skyloop up`` uses it)."""
        c, s, episodes = self.config, self.sim, self.episodes
        s.reset(np.random.default_rng(c.seed))  # warm up: the first scan compiles (numba)
        s.scan()
        episodes.place_on_ground(s.start)  # episode 0's start; its goal is free flight's
        self.service.publish_status(self.clock.stamp(), self.clock.now(), force=True)
        if go is not None:
            self.bus.declare_ready(c.vehicle, "sim")  # what the launcher waits on
            emit(READY_LINE)
        episodes.ground_phase(go)
        self.wait_subscribers()
        self.step.reset_timing()  # the episodes' share only
        t0 = time.monotonic()
        goal = s.goal.copy() if c.free_flight else None
        i = 0
        try:
            if c.goals_from_bus:
                goal = episodes.wait_goal()
            while (i < c.episodes or (c.free_flight and c.episodes <= 0)) \
                    and not self.stopping.is_set() and (goal is not None or not c.free_flight):
                r = episodes.run_episode(i, goal)
                self.results.append(r)
                emit(EPISODE_LINE + json.dumps(r))
                i += 1
                goal = episodes.next_goal(i, r["outcome"])
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
        gate = self.gate
        out.update(steps=steps, mean_steps=steps / n if n else 0.0, wall_s=wall_s,
                   steps_per_s=steps / wall_s if wall_s > 0 else 0.0,
                   stale_commands=gate.stale, late_steps=gate.late, missed_steps=gate.missed,
                   param_rejects=self.service.param_rejects, goal_rejects=self.goal_rejects,
                   **{k: round(v, 3) for k, v in self.step.timing.items()})
        if gate.latencies_ms:
            lat = np.array(gate.latencies_ms)
            out.update(latency_ms_p50=float(np.percentile(lat, 50)),
                       latency_ms_p99=float(np.percentile(lat, 99)),
                       latency_ms_max=float(lat.max()))
        emit(SUMMARY_LINE + json.dumps(out))
        return out
