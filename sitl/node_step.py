"""One control period of the simulator node: pacing, publishing, commands, commander,
flight (:class:`StepLoop`, the base of :class:`sitl.node.SimNode`; the clocks, frames and
rules are described in ``sitl/node.py``'s docstring)."""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from bus import keys
from bus import messages as m
from bus.node import Bus
from bus.task import TASK
from sitl.commander import Commander, State, VehicleSample
from sitl.episode import EpisodeConfig, EpisodeSim
from sitl.flight_model import REST_HEIGHT
from sitl.node_util import quat_from_matrix, quat_from_yaw
from sitl.vehicle_service import VehicleService

log = logging.getLogger("skyloop.sim")
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
    max_steps: int = TASK.max_steps
    goal_radius: float = TASK.goal_radius
    goal_max_altitude: float = TASK.goal_max_altitude
    match_timeout_s: float = 10.0  # wait for subscribers before the first episode
    free_flight: bool = False
    goals_from_bus: bool = False  # free flight toward bus goals only, holding between
    lockstep_timeout_s: float = 2.0
    params: dict[str, float] = field(default_factory=dict)  # bus.params names
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)


class StepLoop:
    """The vehicle's control steps over a :class:`Bus` (see ``sitl/node.py``)."""

    def __init__(self, bus: Bus, config: SimNodeConfig) -> None:
        self.bus = bus
        # the run's own copy with the derived settings; the caller's config stays as given
        free = config.free_flight or config.goals_from_bus
        if free and not config.realtime:  # nothing answers steps for a ground station
            log.info("free flight runs in real time")
        self.config = c = replace(config, free_flight=free, realtime=config.realtime or free,
                                  episode=replace(config.episode, scenario=config.scenario))
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
        self.service.take_setpoints = self._await_command
        for name, value in c.params.items():
            if not self.service.set_param(name, value):
                raise ValueError(f"bad parameter {name}={value!r} (see bus/params.py)")
        area = self.sim.world.scenario.area
        fence = self.commander.config.geofence
        if fence > 0 and (area.size_x**2 + area.size_y**2) ** 0.5 > fence:
            log.warning("scenario %s spans more than GF_MAX_HOR_DIST = %g m: a long flight "
                        "may end in a geofence RTL (the env has no geofence)", c.scenario,
                        fence)
        self.g = 0  # episode control steps over the run (stamps)
        self.vsteps = 0  # every control step flown (the commander's clock)
        self.stale = 0  # commands whose stamp was not the current step's
        self.late = 0  # real time: steps flown on an older command
        self.missed = 0  # lockstep: OFFBOARD steps flown without their command
        self.goal_rejects = 0  # goals from the bus no episode could reach
        self.latencies_ms: list[float] = []
        self._missing = False
        self._last_cmd: Any = None
        self._next_tick: float | None = None
        self._pending_goal: np.ndarray | None = None
        self._resume = State.HOLD  # the mode a placed episode continues in
        self._rejoin_after: float | None = None  # an episode broke then: wait for a rejoin
        self._late_stamp: int | None = None  # the stamp of the step whose command missed
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
            self.service.publish_status(self._stamp(), self.now())  # changes, keepalive
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
        points, lidar = s.scan(), s.lidar.config  # VLP-16 layout: x, y, z, intensity, ring
        cloud = m.pointcloud(points, stamp, rings=m.elevation_rings(
            points, lidar.min_elevation_deg, lidar.max_elevation_deg, lidar.channels))
        t_pub = time.monotonic()
        self.pub[keys.LIDAR_POINTS].put(cloud)
        return t_pub

    # ------------------------------------------------------------------ commands
    def _offer(self, msg: Any) -> None:
        """Offer a ``cmd_vel`` (``VelocitySetpoint``) to the commander."""
        vx, vy, vz, yaw = m.setpoint_values(msg)
        self.commander.setpoint(self.now(), vx, vy, vz, 0.0 if msg.heading else yaw,
                                body=msg.frame == m.FRAME_BODY,
                                yaw=yaw if msg.heading else None)

    def _drain_commands(self) -> None:
        while (msg := self.cmds.get_nowait()) is not None:
            self._offer(msg)
            self._last_cmd = msg

    def _await_command(self, timeout: float) -> bool:
        """Offer the next ``cmd_vel`` (waiting up to ``timeout`` s) and any behind it;
        True if one came (``VehicleService.take_setpoints``)."""
        try:
            msg = self.cmds.get(timeout=timeout)
        except TimeoutError:
            return False
        self._offer(msg)
        self._last_cmd = msg
        self._drain_commands()
        return True

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
                self.service.publish_status(self._stamp(), self.now())
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

    def _take_goal(self, goal: np.ndarray) -> bool:
        """A goal from the bus becomes the pending one unless no episode could reach it
        (not finite, below the terrain, inside an obstacle, higher than
        ``goal_max_altitude + goal_radius``): then it is refused, counted and reported
        (a status event)."""
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
            self.goal_rejects += 1
            log.warning("goal %s refused: %s", goal, why)
            self.service.notify(f"Goal refused: {why}")
            return False
        self._pending_goal = np.asarray(goal, dtype=np.float64)
        return True

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
        while (goal := self.goals.get_nowait()) is not None:  # the newest valid one wins
            self._take_goal(m.pose_values(goal)[0])
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
