"""The scripted straight-line go-to-goal controller: the baseline every policy must beat.

It reads only the newest observation of the 3 x 35 state (abr-method.md layout: 32
faces, then altitude z / 10, h / 180, g / 180) and ignores the LiDAR faces entirely:
fly towards the goal at full speed, hold the flight level, turn to face the goal.
Its success rate per scenario is the "needs the LiDAR" yardstick of the README.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bus.task import TASK
from perception.observation import ObservationConfig


@dataclass
class ScriptedConfig:
    speed: float = TASK.max_action  # m/s towards the goal, the action limit
    flight_level: float = 3.5  # m, p_approAlt
    altitude_gain: float = 1.0  # 1/s, vz = gain * (flight_level - z)
    yaw_gain: float = 1.5  # 1/s, yaw_rate = gain * heading error
    max_action: float = TASK.max_action


class StraightLineController:
    """Maps a (frames, 35) state to a body-horizontal action (vx, vy, vz, yaw_rate)."""

    name = "scripted straight-line controller"

    def __init__(
        self, config: ScriptedConfig | None = None, obs: ObservationConfig | None = None
    ) -> None:
        self.config = config or ScriptedConfig()
        self.obs = obs or ObservationConfig()

    def __call__(self, state: np.ndarray) -> np.ndarray:
        latest = np.asarray(state)[-1]
        z = float(latest[32]) * self.obs.altitude_scale
        h = math.radians(float(latest[33]) * self.obs.angle_scale)  # goal bearing, CCW
        c = self.config
        err = math.atan2(math.sin(h), math.cos(h))  # wrap to (-pi, pi]
        action = np.array(
            [
                c.speed * math.cos(h),
                c.speed * math.sin(h),
                c.altitude_gain * (c.flight_level - z),
                c.yaw_gain * err,
            ]
        )
        return np.clip(action, -c.max_action, c.max_action).astype(np.float32)
