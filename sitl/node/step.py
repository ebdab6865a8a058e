"""One control period of the simulator node (:class:`ControlStep`: pace or gate, publish
the step, take its command, step the commander, fly), the goals it takes from the bus
(:class:`GoalIntake`) and the node's settings (:class:`SimNodeConfig`). The clocks,
frames and rules are described in ``sitl/node/node.py``'s docstring."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from bus import keys
from bus import messages as m
from bus.task import TASK
from sitl.commander.machine import Commander, State, VehicleSample
from sitl.episode import EpisodeConfig, EpisodeSim
from sitl.flight.flight_model import REST_HEIGHT
from sitl.node.pacing import CommandGate, Pacer, StackClock
from sitl.node.util import quat_from_matrix, quat_from_yaw
from sitl.node.vehicle_service import VehicleService

log = logging.getLogger("skyloop.sim")
TOUCHDOWN_SPEED = 1.0  # m/s, a gentler terrain contact outside OFFBOARD is a landing


@dataclass
class SimNodeConfig:
    """What the simulator node runs (env rules are the env's defaults)."""

    scenario: str = "valley"
    episodes: int = 1  # free flight: 0 = until stopped
    seed: int = 0
    vehicle: str = "uav1"
    realtime: bool = False
    max_steps: int = TASK.max_steps
    goal_radius: float = TASK.goal_radius
    goal_max_altitude: float = TASK.goal_max_altitude
    match_timeout_s: float = 10.0  # wait for subscribers before the first episode
    free_flight: bool = False
    goals_from_bus: bool = False  # free flight toward bus goals only, holding between
    lockstep_timeout_s: float = 2.0
    params: dict[str, float] = field(default_factory=dict)  # bus.params names
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)

    def resolved(self) -> SimNodeConfig:
        """A new config with what these settings imply: goals from the bus mean free
        flight; free flight runs in real time (nothing answers steps for a ground
        station); the episode core flies ``scenario``. This one is left as it is."""
        free = self.free_flight or self.goals_from_bus
        return replace(self, free_flight=free, realtime=self.realtime or free,
                       episode=replace(self.episode, scenario=self.scenario))


class GoalIntake:
    """Goals from ``skyloop/<vehicle>/goal``: :meth:`poll` makes the newest valid one
    :attr:`pending` until an episode :meth:`take` s it; a goal no episode could reach
    is refused (:meth:`offer`)."""

    def __init__(self, inbox: Any, config: SimNodeConfig, sim: EpisodeSim,
                 service: VehicleService) -> None:
        self.inbox = inbox
        self.config = config
        self.sim = sim
        self.service = service
        self.pending: np.ndarray | None = None
        self.rejects = 0  # goals from the bus no episode could reach

    def poll(self) -> None:
        while (goal := self.inbox.get_nowait()) is not None:  # the newest valid one wins
            self.offer(m.pose_values(goal)[0])

    def take(self) -> np.ndarray | None:
        goal, self.pending = self.pending, None
        return goal

    def offer(self, goal: np.ndarray) -> bool:
        """``goal`` becomes the pending one unless no episode could reach it (not finite,
        below the terrain, inside an obstacle, higher than ``goal_max_altitude +
        goal_radius``): then it is refused, counted and reported (a status event)."""
        c, s = self.config, self.sim
        why = None
        if not np.all(np.isfinite(goal)):
            why = "not finite"
        elif goal[2] > c.goal_max_altitude + c.goal_radius:
            why = f"above {c.goal_max_altitude + c.goal_radius:g} m"
        elif goal[2] < float(s.world.terrain_height(goal[0], goal[1])):
            why = "below the terrain"
        elif s.world.collides_off_terrain(goal, s.config.body_radius, s.time):
            why = "inside an obstacle"
        if why is not None:
            self.rejects += 1
            log.warning("goal %s refused: %s", goal, why)
            self.service.notify(f"Goal refused: {why}")
            return False
        self.pending = np.asarray(goal, dtype=np.float64)
        return True


class ControlStep:
    """One control period of the vehicle (:meth:`tick`); ``timing``: where its wall time
    went; ``resume``: the mode a placed episode continues in (the commander's before a
    collision of the last step disarmed it)."""

    def __init__(self, config: SimNodeConfig, sim: EpisodeSim, commander: Commander,
                 service: VehicleService, clock: StackClock, pacer: Pacer, gate: CommandGate,
                 goals: GoalIntake, pub: dict[str, Any]) -> None:
        self.config = config
        self.sim = sim
        self.commander = commander
        self.service = service
        self.clock = clock
        self.pacer = pacer
        self.gate = gate
        self.goals = goals
        self.pub = pub
        self.resume = State.HOLD
        self.timing = {"publish_s": 0.0, "wait_s": 0.0, "step_s": 0.0}

    def reset_timing(self) -> None:
        self.timing = dict.fromkeys(self.timing, 0.0)

    def publish(self, episode: int, step: int) -> float:
        """Publish clock, odometry, truth and scan of the current state; return the wall
        time of the scan publish."""
        s, stamp = self.sim, self.clock.stamp()
        est, truth = s.vehicle.estimate, s.vehicle.truth
        self.pub[keys.CLOCK].put(m.step_clock(step, stamp, episode))
        self.pub[keys.ODOM].put(m.odometry(est.position, est.velocity, quat_from_yaw(est.yaw),
                                           stamp))
        self.pub[keys.TRUTH].put(m.odometry(truth.position, truth.velocity,
                                            quat_from_matrix(truth.rotation), stamp))
        # VLP-16 layout: x, y, z, intensity, ring; the lidar knows each return's ring
        # (bus.messages.elevation_rings would recompute it from the point)
        points, rings = s.scan_rings()
        cloud = m.pointcloud(points, stamp, rings=rings)
        t_pub = time.monotonic()
        self.pub[keys.LIDAR_POINTS].put(cloud)
        return t_pub

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
        """One control period (``episode`` None: outside any episode, nothing published
        but the status); returns whether the vehicle collided."""
        c, s, cmdr, clock = self.config, self.sim, self.commander, self.clock
        offboard = cmdr.state == State.OFFBOARD
        gated = episode is not None and offboard and not c.realtime
        t0 = time.perf_counter()
        deadline = None
        if gated:
            self.pacer.release()
        else:
            deadline = self.pacer.pace()
        t1 = t_pubbed = time.perf_counter()
        msg = None
        if episode is not None:
            t_pub = self.publish(episode, s.steps)
            t_pubbed = time.perf_counter()
            if offboard:
                msg = self.gate.wait(t_pub, deadline)
        if not (episode is not None and offboard):
            self.gate.drain()
        t2 = time.perf_counter()
        now = clock.now()
        self.service.serve(now)
        self.goals.poll()
        out = cmdr.step(now, self._sample())
        env_rules = episode is not None and not c.free_flight and cmdr.state == State.OFFBOARD
        if not env_rules:
            x, y = s.vehicle.truth.position[:2]
            s.vehicle.set_ground(float(s.world.terrain_height(x, y)))
        if cmdr.state == State.OFFBOARD and msg is not None and m.is_action(msg):
            collided = s.step_body(np.array(m.setpoint_values(msg), dtype=np.float64))
        else:
            motors = cmdr.armed and cmdr.state != State.ARMED
            collided = s.step_world(np.array(out, dtype=np.float64), motors)
        clock.advance(episode is not None)
        if collided and not env_rules and self._touchdown():
            collided = s.collided = False  # a landing: the step's record says so too
        self.resume = cmdr.state  # the mode the next placed episode continues in
        if collided:
            cmdr.collision(clock.now())
        self.service.publish_status(clock.stamp(), clock.now())
        self.timing["publish_s"] += t_pubbed - t1
        self.timing["wait_s"] += (t1 - t0) + (t2 - t_pubbed)
        self.timing["step_s"] += time.perf_counter() - t2
        return collided
