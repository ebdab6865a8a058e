"""The task specification: the one home of what every part of skyloop agrees on about the
navigation task (abr-method.md, "Task").

- the observation: 32 icosahedron faces + altitude z, goal angles h and g (35 values),
  stacked over ``frames`` = 3 control steps into the state the networks see;
- the action: body-horizontal (vx, vy, vz, yaw_rate), each in [-max_action, max_action];
- the episode limits and the outcome: a collision ends an episode, reaching within
  ``goal_radius`` of the goal at an altitude not above ``goal_max_altitude`` is success
  (both terminal), ``max_steps`` control steps is a timeout (a truncation, not terminal);
- the goal angles h and g (:func:`goal_angles`) the observation and eq. 3.5 take;
- the step record (:class:`StepRecord`): what the simulator's episode core
  (``sitl.episode.EpisodeSim.record``) says of each control step -- D_pre, D_cur,
  altitude, h, g, collision and outcome -- from which the outcome, the termination and
  eq. 3.5's reward (``policy.algorithms.rewards.step_reward``) all derive, in the env,
  in the simulator node (which publishes it, ``skyloop/<vehicle>/step_record``) and in
  training from logs.

The simulator (``sitl``), perception, the in-process env, training, rollouts, the logs'
readers and the policy node all read these values from here (``TASK``, or a ``TaskSpec``
replaced field by field where a run overrides a limit), so none of them spells 35, 2.0
or 300 itself.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from typing import Any

__all__ = ["MIN_SPEED", "OUTCOME_LIMITS", "TASK", "StepRecord", "TaskSpec", "episode_outcome",
           "goal_angles"]

#: Horizontal speed (m/s) below which g is measured from the heading instead of the
#: velocity (the velocity direction of a hovering UAV is estimator noise).
MIN_SPEED = 0.1

#: Of the limits an episode runs under and its log records (``EpisodeEvent`` START:
#: max_steps, goal_radius, goal_max_altitude), those that decide success, hence the
#: terminal flag and the goal reward of a logged episode: a learner trains only on
#: episodes run under its own. (``max_steps`` only truncates, which is not terminal: any
#: value serves.)
OUTCOME_LIMITS = ("goal_radius", "goal_max_altitude")


@dataclass(frozen=True)
class TaskSpec:
    """Shapes, scales and limits of the navigation task (defaults: the paper's Table 4.1
    and abr-method.md)."""

    frames: int = 3  # p_frames: observations stacked into one state
    faces: int = 32  # truncated icosahedron faces
    action_dim: int = 4  # l_x, l_y, l_z (m/s), a_z (rad/s)
    max_action: float = 2.0  # each action in [-max_action, max_action]
    max_steps: int = 300  # control steps before a timeout
    goal_radius: float = 2.0  # m, horizontal and vertical distance to the goal
    goal_max_altitude: float = 6.0  # m, success only at or below this altitude
    # What the policy is trained under and the vehicle can change (``bus.params``
    # marks these parameters ``task_field``): an actor records them; the policy node
    # does not fly under other values.
    ico_radius: float = 4.0  # m, p_radius of the observation (eq. 3.1) [SKY_ICO_RADIUS]
    max_speed_xy: float = 2.0  # m/s, the autopilot's horizontal limit [MPC_XY_VEL_MAX]
    max_speed_z: float = 2.0  # m/s, the autopilot's vertical limit [MPC_Z_VEL_MAX]

    @property
    def obs_dim(self) -> int:
        """Values of one observation: the faces, then z, h, g."""
        return self.faces + 3

    @property
    def state_shape(self) -> tuple[int, int]:
        """(frames, obs_dim): the state the networks see, oldest frame first."""
        return (self.frames, self.obs_dim)

    @property
    def state_dim(self) -> int:
        return self.frames * self.obs_dim

    def outcome(self, collided: bool, distance: float, altitude: float,
                steps: int | float) -> str | None:
        """How the episode ends after this step: ``success``, ``collision``, ``timeout``,
        or None while it goes on. ``steps`` counts the control steps taken so far."""
        if collided:
            return "collision"
        if distance <= self.goal_radius and altitude <= self.goal_max_altitude:
            return "success"
        if steps >= self.max_steps:
            return "timeout"
        return None

    def step_record(self, episode: int, step: int, distance_before: float, distance: float,
                    altitude: float, h: float, g: float, collided: bool) -> StepRecord:
        """The record of one control step under this task: its outcome is
        :meth:`outcome` of it (``step`` control steps taken)."""
        return StepRecord(int(episode), int(step), float(distance_before), float(distance),
                          float(altitude), float(h), float(g), bool(collided),
                          self.outcome(collided, distance, altitude, step))

    def limits_mismatch(self, recorded: dict[str, float] | None) -> str | None:
        """Why an episode run under the ``recorded`` limits (``bus.messages.episode_limits``)
        cannot train under this task, or None when it can (the same ``OUTCOME_LIMITS``)."""
        if recorded is None:
            return "its START records no episode limits (goal_radius 0)"
        diff = [f"{name} {recorded[name]:g} (this task: {getattr(self, name):g})"
                for name in OUTCOME_LIMITS if recorded[name] != getattr(self, name)]
        return "run under " + ", ".join(diff) if diff else None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "task") -> TaskSpec:
        """A spec from ``to_dict`` output; unknown or mistyped fields raise ValueError
        naming ``where`` and the field."""
        known = {f.name: f.type for f in fields(cls)}
        for key, value in data.items():
            if key not in known:
                raise ValueError(f"{where}: unknown task field {key!r}")
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                raise ValueError(f"{where}: task field {key!r} must be a number, got {value!r}")
            if known[key] == "int" and value != int(value):
                raise ValueError(f"{where}: task field {key!r} must be an integer, got {value!r}")
        return cls(**{k: (int(v) if known[k] == "int" else float(v)) for k, v in data.items()})


TASK = TaskSpec()


@dataclass(frozen=True)
class StepRecord:
    """One control step of an episode as the simulator's episode core judged it: every
    input of eq. 3.5's base reward, the collision and the outcome (``TaskSpec.outcome``).
    Built by :meth:`TaskSpec.step_record` (``sitl.episode.EpisodeSim.record``), carried
    on the bus and in logs as ``skyloop_msgs/StepRecord`` (``bus.messages.step_record``).
    Distances and altitude are of the *true* pose, h and g of the *estimate* (what the
    observation holds), all after the step."""

    episode: int  # the episode's index (the EpisodeEvent's)
    step: int  # control steps taken in the episode: 1 after the first
    distance_before: float  # m, D_pre: true distance to the goal before the step
    distance: float  # m, D_cur: after it
    altitude: float  # m, true z after the step
    h: float  # deg in [0, 360): heading to the goal's direction (goal_angles)
    g: float  # deg in [0, 360): horizontal velocity to the goal's direction
    collided: bool
    outcome: str | None  # success, collision, timeout; None while the episode goes on

    @property
    def goal_reached(self) -> bool:
        return self.outcome == "success"

    @property
    def terminated(self) -> bool:
        """Terminal for the critic target: success or collision (a timeout is not)."""
        return self.outcome in ("success", "collision")

    @property
    def truncated(self) -> bool:
        return self.outcome == "timeout"


def _wrap_deg(angle_rad: float) -> float:
    """Radians -> degrees in [0, 360) (guarding the float rounding of -tiny % 360)."""
    deg = math.degrees(angle_rad) % 360.0
    return 0.0 if deg >= 360.0 else deg


def goal_angles(
    position: Sequence[float],
    yaw: float,
    velocity: Sequence[float],
    goal: Sequence[float],
    min_speed: float = MIN_SPEED,
) -> tuple[float, float]:
    """The observation angles (h_deg, g_deg), each in [0, 360).

    World frame ENU, ``yaw`` in radians (0 = facing east, counterclockwise positive).
    Both angles are measured **counterclockwise** (seen from above) from the reference
    direction to the horizontal direction of the goal ``goal - position``: a goal
    straight ahead gives 0, to the left 90, behind 180, to the right 270.

    - h: reference = the UAV's heading ``(cos yaw, sin yaw)``.
    - g **[choice]**: reference = the UAV's horizontal velocity. When the horizontal
      speed is below ``min_speed`` (default 0.1 m/s, e.g. hovering at episode start)
      the velocity direction is noise, so the heading is used instead and g = h.
    - When the goal is horizontally at the UAV's position (its direction undefined),
      both angles are 0.
    """
    dx = float(goal[0]) - float(position[0])
    dy = float(goal[1]) - float(position[1])
    if dx == 0.0 and dy == 0.0:
        return 0.0, 0.0
    bearing = math.atan2(dy, dx)
    h = _wrap_deg(bearing - float(yaw))
    vx, vy = float(velocity[0]), float(velocity[1])
    if math.hypot(vx, vy) < min_speed:
        return h, h
    return h, _wrap_deg(bearing - math.atan2(vy, vx))


def episode_outcome(goal_reached: bool, collision: bool) -> str:
    """The outcome of a finished episode from its last step's flags."""
    return "success" if goal_reached else "collision" if collision else "timeout"
