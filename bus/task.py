"""The task specification: the one home of what every part of skyloop agrees on about the
navigation task (abr-method.md, "Task").

- the observation: 32 icosahedron faces + altitude z, goal angles h and g (35 values),
  stacked over ``frames`` = 3 control steps into the state the networks see;
- the action: body-horizontal (vx, vy, vz, yaw_rate), each in [-max_action, max_action];
- the episode limits and the outcome: a collision ends an episode, reaching within
  ``goal_radius`` of the goal at an altitude not above ``goal_max_altitude`` is success
  (both terminal), ``max_steps`` control steps is a timeout (a truncation, not terminal).

The simulator (``sitl``), perception, the in-process env, training, rollouts, the logs'
readers and the policy node all read these values from here (``TASK``, or a ``TaskSpec``
replaced field by field where a run overrides a limit), so none of them spells 35, 2.0
or 300 itself.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

__all__ = ["OUTCOME_LIMITS", "TASK", "TaskSpec", "episode_outcome"]

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


def episode_outcome(goal_reached: bool, collision: bool) -> str:
    """The outcome of a finished episode from its last step's flags."""
    return "success" if goal_reached else "collision" if collision else "timeout"
