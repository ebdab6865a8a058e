"""The simulator side of one episode: world, vehicle, LiDAR and collision, seeded.

This is the piece the in-process env (``policy.training.env``) and the simulator node share, so
that an episode flown through the process graph in lockstep reproduces the same
episode in the env: same seed -> same start, goal, initial yaw, sensor noise; same
setpoints -> same trajectory.

Reset draws, from ``numpy.random.default_rng(seed)`` (the same generator Gymnasium's
``reset(seed=...)`` builds): start and goal (``World.sample_start_goal``), the initial
yaw uniform in [-pi, pi), then one sub-seed for the vehicle's sensors (the LiDAR noise
uses sub-seed + 1). With a family or a mixture of worlds (``sitl.world.families``), reset
first draws the world (family, then seed) from the same generator.

After each control step of an episode, :meth:`EpisodeSim.record` gives the step's
:class:`bus.task.StepRecord` (D_pre, D_cur, altitude, h, g, collision, outcome under a
``TaskSpec``): the one place the env and the simulator node take the outcome, the
termination and (through ``policy.algorithms.rewards.step_reward``) the reward from.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import numpy as np

from bus.task import TASK, StepRecord, TaskSpec, goal_angles
from sitl.flight.vehicle import Vehicle, VehicleConfig
from sitl.lidar.scanner import Lidar, LidarConfig
from sitl.world.families import WorldSource
from sitl.world.world import UAV_BODY_RADIUS, World, load_scenario

WORLD_CACHE = 4  # worlds kept built (evaluation cycles through a few)
#: the LiDAR's range beyond the observation's icosahedron radius: the default 4.5 m range
#: for the default 4 m radius (points beyond the radius are not in the faces, but the range
#: still matters a little: the LiDAR's noise stream is drawn per return within range), so an
#: actor trained with radius r flies with range r + this, in training, evaluation and the
#: stack alike (``EpisodeSim.ico_radius``, set by ``SKY_ICO_RADIUS``)
LIDAR_MARGIN = 0.5


@dataclass
class EpisodeConfig:
    scenario: str = "valley"  # a world, or worlds drawn per episode (sitl.world.families)
    world_every: int = 1  # family:/mix: scenarios: a new world every N episodes
    lidar_max_range: float = TASK.ico_radius + LIDAR_MARGIN  # the faces need p_radius = 4 m
    lidar_noise_sigma: float = 0.03
    body_radius: float = UAV_BODY_RADIUS
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)


def body_to_world(command: np.ndarray, yaw: float) -> np.ndarray:
    """Rotate a body-horizontal (forward, left, up, yaw_rate) command into world ENU."""
    c, s = math.cos(yaw), math.sin(yaw)
    vx, vy, vz, yaw_rate = (float(a) for a in command)
    return np.array([c * vx - s * vy, s * vx + c * vy, vz, yaw_rate])


class EpisodeSim:
    """World + JSBSim vehicle + VLP-16 for seeded episodes, one control period a step."""

    def __init__(self, config: EpisodeConfig | None = None) -> None:
        self.config = c = config or EpisodeConfig()
        if c.world_every < 1:
            raise ValueError(f"world_every must be 1 or more, got {c.world_every}")
        self.source = WorldSource.parse(c.scenario)
        self.vehicle = Vehicle(c.vehicle)
        self._worlds: OrderedDict[str, tuple[World, Lidar]] = OrderedDict()
        self.world_builds = 0
        self.use_world(self.source.template())
        self.start = self.goal = np.zeros(3)
        self.time = 0.0
        self.steps = 0
        self.episodes = 0
        self.collided = False
        # true distances to the goal before and after the last step (D_pre, D_cur)
        self.distance_before = self.distance = 0.0

    def use_world(self, name: str) -> None:
        """Fly world ``name`` from the next episode on (built once; the last few kept)."""
        if name not in self._worlds:
            world = World(load_scenario(name))
            self._worlds[name] = (world, Lidar(world, LidarConfig(
                max_range=self.config.lidar_max_range,
                noise_sigma=self.config.lidar_noise_sigma)))
            self.world_builds += 1
            while len(self._worlds) > WORLD_CACHE:
                self._worlds.popitem(last=False)
        self._worlds.move_to_end(name)
        self.world_name = name
        self.world, self.lidar = self._worlds[name]

    @property
    def ico_radius(self) -> float:
        """The observation radius the LiDAR reaches (its range less ``LIDAR_MARGIN``)."""
        return self.config.lidar_max_range - LIDAR_MARGIN

    @ico_radius.setter
    def ico_radius(self, radius: float) -> None:
        """Make the LiDAR reach an observation of radius ``radius`` (``SKY_ICO_RADIUS``,
        ``bus.params``): its range becomes ``radius + LIDAR_MARGIN``, for every world
        built and to come, from the next scan on (its noise stream goes on)."""
        max_range = float(radius) + LIDAR_MARGIN
        if math.isclose(max_range, self.config.lidar_max_range):
            return
        self.config = replace(self.config, lidar_max_range=max_range)
        for _, lidar in self._worlds.values():
            lidar.set_max_range(max_range)

    def reset(self, rng: np.random.Generator, goal: np.ndarray | None = None) -> None:
        """Start a new episode with randomness drawn from ``rng`` (see module docstring);
        with a family or mixture, a new world first (every ``world_every`` episodes),
        drawn from ``rng`` too."""
        if not self.source.fixed and self.episodes % self.config.world_every == 0:
            self.use_world(self.source.draw(rng))
        self.episodes += 1
        self.start, self.goal = self.world.sample_start_goal(rng)
        if goal is not None:
            self.goal = np.asarray(goal, dtype=float)
        yaw = float(rng.uniform(-np.pi, np.pi))
        sub_seed = int(rng.integers(2**31))
        self.vehicle.reset(self.start, yaw, seed=sub_seed)
        self.lidar.reseed(sub_seed + 1)
        self.time, self.steps, self.collided = 0.0, 0, False
        self.distance_before = self.distance = self.goal_distance()

    def step_body(self, command: np.ndarray) -> bool:
        """Fly one control period on a body-horizontal command; returns ``collided``.

        The command is rotated into the world frame with the *estimated* yaw, as a flight
        controller does with a body-frame setpoint.
        """
        return self.step_world(body_to_world(command, self.vehicle.estimate.yaw))

    def new_goal(self, goal: np.ndarray) -> None:
        """Start a new episode from where the vehicle is, toward ``goal`` (the sim node's
        free flight and goals from the bus): steps restart, time and vehicle go on."""
        self.start = self.vehicle.truth.position.copy()
        self.goal = np.asarray(goal, dtype=float).copy()
        self.steps, self.collided = 0, False
        self.distance_before = self.distance = self.goal_distance()

    def place_on_ground(self, x: float, y: float, yaw: float) -> None:
        """Stand the vehicle on the terrain at (x, y), motors stopped (the simulator
        node's ground phase; the JSBSim ground is put at the terrain's height there)."""
        ground = float(self.world.terrain_height(x, y))
        self.vehicle.reset(np.array([x, y, ground]), yaw, on_ground=True)
        self.collided = False

    def step_world(self, setpoint: np.ndarray, motors: bool = True) -> bool:
        """Fly one control period on a world ENU (vx, vy, vz, yaw_rate) setpoint
        (``motors`` False: stopped, see ``Vehicle.step``)."""
        self.vehicle.step(setpoint, motors)
        self.time += self.vehicle.config.control_period
        self.steps += 1
        self.collided = self.world.collides(self.vehicle.truth.position,
                                            self.config.body_radius, self.time)
        self.distance_before, self.distance = self.distance, self.goal_distance()
        return self.collided

    def record(self, task: TaskSpec, episode: int = 0) -> StepRecord:
        """The :class:`~bus.task.StepRecord` of the step just flown, as episode
        ``episode`` of ``task``: D_pre and D_cur (true distances to the goal before and
        after it), the true altitude, h and g from the *estimate* (as the observation
        has them, :func:`bus.task.goal_angles`), ``collided``, and ``task.outcome`` of it
        after :attr:`steps` steps."""
        est = self.vehicle.estimate
        h, g = goal_angles(est.position, est.yaw, est.velocity, self.goal)
        return task.step_record(episode, self.steps, self.distance_before, self.distance,
                                float(self.vehicle.truth.position[2]), h, g, self.collided)

    def scan(self) -> np.ndarray:
        """A VLP-16 scan at the true pose, now: float32 (N, 3) in the sensor frame."""
        truth = self.vehicle.truth
        return self.lidar.scan(truth.position, truth.rotation, self.time)

    def scan_rings(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`scan` and each return's ring (``Lidar.scan_rings``)."""
        truth = self.vehicle.truth
        return self.lidar.scan_rings(truth.position, truth.rotation, self.time)

    def goal_distance(self) -> float:
        return float(np.linalg.norm(self.vehicle.truth.position - self.goal))
