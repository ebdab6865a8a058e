"""The in-process Gymnasium environment ``skyloop/UavNav-v0`` (abr-method.md, "Task").

One control step (0.1 s) is the same pipeline the process graph runs, in one process:

    action (body-horizontal vx, vy, vz, yaw_rate) -> world ENU velocity setpoint
    -> JSBSim F450 + velocity autopilot for 50 physics steps (sitl.flight.vehicle)
    -> collision check of the true body sphere (sitl.world.world)
    -> VLP-16 scan at the true pose (sitl.lidar.scanner)
    -> 32 icosahedron faces + altitude, h, g from the estimate (perception)
    -> the step's record (``EpisodeSim.record``: D_pre, D_cur, altitude, h, g,
       collision, outcome; ``info["record"]``) -> reward eq. 3.5 from it
       (``policy.algorithms.rewards.step_reward``)
    -> the stacked state (perception.FrameStacker, EnvConfig.frames)

Episode ends (abr-method.md, ``TaskSpec.outcome`` in the record): goal reached (within
``goal_radius`` = 2 m of the goal and altitude not above ``goal_max_altitude`` = 6 m) or
collision are terminal; 300 steps is a truncation (not terminal for the critic target).

Actions: NaN or inf raise ``ValueError`` (a clear error rather than a silently held
setpoint); finite values outside [-2, 2] are clipped. Actions are rounded to float32
before use, as the MAVLink path carries float32, so the env and the stack agree.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from bus.task import TASK, StepRecord, TaskSpec
from perception.icosahedron import TruncatedIcosahedron
from perception.observation import FrameStacker, ObservationConfig, observation_from_scan
from policy.algorithms.rewards import RewardConfig, step_reward
from sitl.episode import EpisodeConfig, EpisodeSim, body_to_world
from sitl.render.frames import FastRenderer

OBS_DIM, MAX_ACTION = TASK.obs_dim, TASK.max_action  # bus.task
RENDER_BACKENDS = ("fast", "matplotlib")  # rgb_array: sitl.render.frames, .scene


@dataclass
class EnvConfig:
    """Episode limits and the shape of the state (defaults: the task specification,
    ``bus.task``) and the scenario."""

    max_steps: int = TASK.max_steps
    goal_radius: float = TASK.goal_radius
    goal_max_altitude: float = TASK.goal_max_altitude
    frames: int = TASK.frames  # p_frames: observations stacked into one state
    ico_radius: float = TASK.ico_radius  # p_radius of the observation's icosahedron, m
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)  # scenario, LiDAR range

    @property
    def task(self) -> TaskSpec:
        """The task specification with this config's limits and state shape."""
        return replace(TASK, max_steps=self.max_steps, goal_radius=self.goal_radius,
                       goal_max_altitude=self.goal_max_altitude, frames=self.frames,
                       ico_radius=self.ico_radius)


__all__ = ["EnvConfig", "UavNavEnv", "body_to_world"]


class UavNavEnv(gymnasium.Env):
    """Navigate the F450 from a random start to a random goal using LiDAR observations."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        scenario: str = "valley",
        seed: int | None = None,
        lidar_max_range: float = 4.5,
        render_mode: str | None = None,
        config: EnvConfig | None = None,
        reward_config: RewardConfig | None = None,
        observation_config: ObservationConfig | None = None,
        render_backend: str = "fast",
        world_every: int = 1,
    ) -> None:
        self.config = config or EnvConfig(
            episode=EpisodeConfig(scenario=scenario, lidar_max_range=lidar_max_range,
                                  world_every=world_every))
        self.reward_config = reward_config or RewardConfig()
        self.task = self.config.task
        self.obs_config = observation_config or ObservationConfig(radius=self.task.ico_radius)
        if self.obs_config.radius != self.task.ico_radius:
            raise ValueError(f"observation_config.radius {self.obs_config.radius} differs "
                             f"from the task's ico_radius {self.task.ico_radius}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', not {render_mode!r}")
        self.render_mode = render_mode
        if render_backend not in RENDER_BACKENDS:
            raise ValueError(f"render_backend must be one of {RENDER_BACKENDS}, "
                             f"not {render_backend!r}")
        self.render_backend = render_backend
        self._renderer: FastRenderer | None = None  # built on the first frame of a world
        self.sim = EpisodeSim(self.config.episode)
        self.world, self.vehicle, self.lidar = self.sim.world, self.sim.vehicle, self.sim.lidar
        self.ico = TruncatedIcosahedron(self.obs_config.radius)
        self.stacker = FrameStacker(self.task.frames, OBS_DIM)
        self.action_space = spaces.Box(-MAX_ACTION, MAX_ACTION, (TASK.action_dim,), np.float32)
        # Scaled attributes: faces in [0, 2], altitude z/10 (|z| <= 100 m), h and g in [0, 2).
        self.observation_space = spaces.Box(-10.0, 10.0, self.task.state_shape, np.float32)
        self._seed = seed
        self._faces = np.zeros(32, np.float32)
        self._points = np.zeros((0, 3), np.float32)
        self.path: list[np.ndarray] = []
        self.steps = 0
        self.record: StepRecord | None = None  # the last step's (None before the first)

    # -- Gymnasium API ---------------------------------------------------------------

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is None and self._seed is not None:
            seed, self._seed = self._seed, None
        super().reset(seed=seed)
        self.sim.reset(self.np_random, goal=(options or {}).get("goal"))
        self.world, self.lidar = self.sim.world, self.sim.lidar  # a drawn world: its own
        self.steps = 0
        self.record = None
        self.stacker.reset()
        self.path = [self.vehicle.truth.position.copy()]
        obs = self._observe()
        return self.stacker.push(obs), self._info(collided=False, reached=False, parts={})

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        action = np.asarray(action, dtype=np.float64).reshape(-1)
        if action.shape != (TASK.action_dim,):
            raise ValueError(f"action must be (vx, vy, vz, yaw_rate), got shape {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action must be finite, got {action.tolist()}")
        action = np.clip(action, -MAX_ACTION, MAX_ACTION).astype(np.float32)

        self.sim.step_body(action)
        self.steps += 1
        self.path.append(self.vehicle.truth.position.copy())
        obs = self._observe()
        # episode 0: an env numbers no episodes (same seed, same info; a log renumbers)
        self.record = rec = self.sim.record(self.task)
        reward, parts = step_reward(rec, self.reward_config)
        info = self._info(collided=rec.collided, reached=rec.goal_reached, parts=parts)
        info["record"] = rec
        return self.stacker.push(obs), float(reward), rec.terminated, rec.truncated, info

    def render(self) -> np.ndarray | None:
        """The current frame as RGB uint8 with ``render_mode="rgb_array"`` (else None).

        ``render_backend="fast"`` (default): 640x480 from :mod:`sitl.render.frames`, a
        top-down map (terrain, obstacles, aircraft, goal, trail, LiDAR returns, the
        vehicle and its icosahedron ring) and a panel (face charts, altitude and
        distance-to-goal charts, status); the map is precomputed on the first frame of a
        world (~0.1 s), then a frame takes milliseconds, so ``RecordVideo`` is
        practical. ``"matplotlib"``: the 960x480 picture of :mod:`sitl.render.scene` (top and
        3D views), about a second a frame.
        """
        if self.render_mode != "rgb_array":
            return None
        truth = self.vehicle.truth
        if self.render_backend == "fast":
            world = self.sim.world
            if self._renderer is None or not self._renderer.matches(world):
                self._renderer = FastRenderer(
                    world, face_normals=self.ico.normals, ico_radius=self.ico.radius,
                    face_scale=(1.0 if self.obs_config.encoding == "proximity"
                                else self.ico.radius),
                    max_steps=self.task.max_steps, goal_radius=self.task.goal_radius,
                    goal_max_altitude=self.task.goal_max_altitude,
                    lidar_range=self.config.episode.lidar_max_range)
            outcome = self.record.outcome if self.record is not None else None
            return self._renderer.frame(
                position=truth.position, rotation=truth.rotation, path=np.array(self.path),
                start=self.start, goal=self.goal, points=self._points,
                face_values=self._faces, velocity=truth.velocity, t=self.sim.time,
                step=self.steps, outcome=outcome)
        from sitl.render.scene import render_scene

        return render_scene(
            self.world,
            start=self.start,
            goal=self.goal,
            position=truth.position,
            rotation=truth.rotation,
            points=self._points,
            face_values=self._faces,
            face_normals=self.ico.normals,
            paths=[np.array(self.path)],
            title=f"{self.config.episode.scenario} step {self.steps}",
            size=(960, 480),
        )

    # -- internals -------------------------------------------------------------------

    @property
    def start(self) -> np.ndarray:
        return self.sim.start

    @property
    def goal(self) -> np.ndarray:
        return self.sim.goal

    def _observe(self) -> np.ndarray:
        """One 35-attribute observation: faces from the scan, z/h/g from the estimate."""
        est = self.vehicle.estimate
        self._points = self.sim.scan()
        obs, self._faces, _, _ = observation_from_scan(
            self._points, self.ico, est.position, est.yaw, est.velocity, self.goal,
            self.obs_config)
        return obs

    def _info(self, *, collided: bool, reached: bool, parts: dict[str, float]) -> dict[str, Any]:
        return {
            "distance_to_goal": self.sim.distance,
            "collision": bool(collided),
            "goal_reached": bool(reached),
            "reward_components": dict(parts),
            "position": self.vehicle.truth.position.copy(),
            "goal": self.goal.copy(),
            "steps": self.steps,
            "world": self.sim.world_name,  # the drawn world's NAME#SEED (sitl.world.families)
        }
