"""The 35-attribute observation and the 3-frame state (paper section 3.2, abr-method.md "Task").

Observation ``o = (f_1..f_32, z, h, g)``; the state is the last p_frames = 3 observations,
stacked FIFO (oldest first), zero-padded at episode start (Algorithm 3.1:
``s(0, 0, ..., o)``) and never spanning two episodes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from bus.task import TASK, goal_angles
from perception.faces import ENCODINGS, face_values
from perception.icosahedron import N_FACES, TruncatedIcosahedron

OBS_DIM = TASK.obs_dim  # the faces, z, h, g
assert TASK.faces == N_FACES, "the task's faces are the truncated icosahedron's"


@dataclass
class ObservationConfig:
    """Scaling of the network inputs **[choice]** (abr-method.md): f / radius,
    z / altitude_scale, h / angle_scale, g / angle_scale.

    With the default scaling h and g land in [0, 2), not [-1, 1]: "goal straight ahead"
    sits at the wrap-around (h = 359 deg -> 1.99, h = 1 deg -> 0.006), the most common
    situation of a successful flight. ``centre_angles=True`` maps the angles to
    [-180, 180) before scaling, so they land in [-1, 1) with the discontinuity moved
    to "goal straight behind"; we think that is the better input, but the default keeps
    the abr-method scaling.

    ``encoding`` must match the one used for :func:`perception.faces.face_values`:
    "distance" values (metres) are divided by ``radius``; "proximity" values are
    already in [0, 1] and are used as they are.
    """

    radius: float = TASK.ico_radius  # SKY_ICO_RADIUS
    altitude_scale: float = 10.0
    angle_scale: float = 180.0
    encoding: str = "distance"
    centre_angles: bool = False

    def __post_init__(self) -> None:
        if self.encoding not in ENCODINGS:
            raise ValueError(f"encoding must be one of {ENCODINGS}, got {self.encoding!r}")
        for name in ("radius", "altitude_scale", "angle_scale"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive and finite, got {value!r}")


def scaling_fields(config: ObservationConfig) -> dict[str, float | bool | str]:
    """The configuration as the Observation message records it (``bus.messages``
    ``SCALING_FIELDS``)."""
    return asdict(config)


def config_from_scaling(fields: Mapping[str, Any]) -> ObservationConfig:
    """The :class:`ObservationConfig` an Observation message recorded
    (:func:`bus.messages.observation_scaling`); ``ValueError`` if it is not one."""
    return ObservationConfig(radius=float(fields["radius"]),
                             altitude_scale=float(fields["altitude_scale"]),
                             angle_scale=float(fields["angle_scale"]),
                             encoding=str(fields["encoding"]),
                             centre_angles=bool(fields["centre_angles"]))


def goal_terms(obs: np.ndarray, config: ObservationConfig) -> tuple[float, float, float]:
    """The inverse of :func:`goal_slots`: (altitude m,
    h_deg, g_deg) with the angles in [0, 360), as eq. 3.5 takes them."""
    z, h, g = (float(v) for v in obs[N_FACES:N_FACES + 3])
    return (z * config.altitude_scale, (h * config.angle_scale) % 360.0,
            (g * config.angle_scale) % 360.0)


def build_observation(
    face_values: np.ndarray,
    altitude: float,
    h_deg: float,
    g_deg: float,
    config: ObservationConfig | None = None,
) -> np.ndarray:
    """(35,) float32 observation ``(f_1..f_32, z, h, g)``, scaled per ``config``.

    ``f / radius`` (distance encoding; proximity values unscaled), ``z / altitude_scale``,
    ``h / angle_scale``, ``g / angle_scale`` (h, g in [0, 2) by default, [-1, 1) with
    ``centre_angles``). Raises ValueError on a wrong shape or non-finite input: a NaN
    must not reach the policy silently.
    """
    cfg = config if config is not None else ObservationConfig()
    f = np.asarray(face_values, dtype=np.float64)
    if f.shape != (N_FACES,):
        raise ValueError(f"face_values must have shape ({N_FACES},), got {f.shape}")
    h, g, z = float(h_deg), float(g_deg), float(altitude)
    if not (np.isfinite(f).all() and math.isfinite(z) and math.isfinite(h)
            and math.isfinite(g)):
        raise ValueError("observation inputs must be finite")
    out = np.empty(OBS_DIM, dtype=np.float32)
    out[:N_FACES] = f / cfg.radius if cfg.encoding == "distance" else f
    out[N_FACES:] = goal_slots(z, h, g, cfg)
    return out


def goal_slots(altitude: float, h_deg: float, g_deg: float,
               config: ObservationConfig) -> tuple[float, float, float]:
    """The observation's last three slots: z / altitude_scale, h / angle_scale,
    g / angle_scale (the angles first moved to [-180, 180) with ``centre_angles``)."""
    h, g = float(h_deg), float(g_deg)
    if config.centre_angles:
        h = (h + 180.0) % 360.0 - 180.0
        g = (g + 180.0) % 360.0 - 180.0
    return (float(altitude) / config.altitude_scale, h / config.angle_scale,
            g / config.angle_scale)


class FrameStacker:
    """FIFO stack of the last ``frames`` observations: the state ``(o_1, ..., o_p)``.

    Row 0 is the oldest, the last row the newest. After :meth:`reset` the stack is all
    zeros, so the first push gives ``(0, 0, o)`` (Algorithm 3.1). Call :meth:`reset` at
    every episode start: a stack never spans two episodes.
    """

    def __init__(self, frames: int = TASK.frames, dim: int = OBS_DIM) -> None:
        if frames < 1 or dim < 1:
            raise ValueError(f"frames and dim must be >= 1, got {frames}, {dim}")
        self.frames = int(frames)
        self.dim = int(dim)
        self._buf = np.zeros((self.frames, self.dim), dtype=np.float32)
        self.count = 0  # observations pushed since the last reset

    def reset(self) -> None:
        """Zero-fill: start of a new episode."""
        self._buf.fill(0.0)
        self.count = 0

    def push(self, obs: np.ndarray) -> np.ndarray:
        """Append ``obs`` (shape (dim,)) as the newest frame; return a (frames, dim)
        float32 copy of the stack."""
        o = np.asarray(obs, dtype=np.float32)
        if o.shape != (self.dim,):
            raise ValueError(f"obs must have shape ({self.dim},), got {o.shape}")
        self._buf[:-1] = self._buf[1:]
        self._buf[-1] = o
        self.count += 1
        return self._buf.copy()

    @property
    def state(self) -> np.ndarray:
        """A copy of the current stack without pushing."""
        return self._buf.copy()


def observation_from_scan(
    points: np.ndarray,
    ico: TruncatedIcosahedron,
    position: np.ndarray,
    yaw: float,
    velocity: np.ndarray,
    goal: np.ndarray,
    config: ObservationConfig,
) -> tuple[np.ndarray, np.ndarray, float, float]:
    """One 35-attribute observation from a scan and the estimated state.

    The whole of perception for one step, shared by the in-process env and the
    perception node: face values (eq. 3.1-3.2), the goal angles h and g, the altitude.
    Returns ``(observation, face_values, h_deg, g_deg)``.
    """
    faces = face_values(points, ico, config.encoding)
    h_deg, g_deg = goal_angles(position, yaw, velocity, goal)
    obs = build_observation(faces, float(position[2]), h_deg, g_deg, config)
    return obs, faces, h_deg, g_deg
