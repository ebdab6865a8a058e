"""Moving aircraft: yawed boxes flying closed waypoint loops at constant speed.

An aircraft starts at fraction ``phase`` of its loop at t = 0, moves along the
polyline (last waypoint back to the first) at ``speed`` and keeps its box level,
yawed along the current segment. Pose evaluation is a numba kernel so that
``World.collides`` stays in the microseconds; the same kernel serves the LiDAR.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from sitl.world.scenario import AircraftConfig


@dataclass
class Fleet:
    """All aircraft of a scenario as padded arrays."""

    waypoints: np.ndarray  # (K, W+1, 3), the loop closed (first point repeated), padded
    cumlen: np.ndarray  # (K, W+1) arc length at each waypoint
    count: np.ndarray  # (K,) int64 number of loop points (W_k + 1)
    params: np.ndarray  # (K, 6): speed, start arc length, total length, hx, hy, hz

    @classmethod
    def from_config(cls, aircraft: tuple[AircraftConfig, ...]) -> Fleet:
        k = len(aircraft)
        wmax = max((len(a.waypoints) for a in aircraft), default=1) + 1
        wps = np.zeros((k, wmax, 3))
        cum = np.zeros((k, wmax))
        count = np.zeros(k, np.int64)
        params = np.zeros((k, 6))
        for i, a in enumerate(aircraft):
            loop = np.array(list(a.waypoints) + [a.waypoints[0]], float)
            seg = np.linalg.norm(np.diff(loop, axis=0), axis=1)
            c = np.concatenate([[0.0], np.cumsum(seg)])
            n = len(loop)
            wps[i, :n], cum[i, :n], count[i] = loop, c, n
            wps[i, n:], cum[i, n:] = loop[-1], c[-1]
            total = float(c[-1])
            params[i] = [a.speed, a.phase * total, total, *(np.array(a.size) / 2)]
        return cls(wps, cum, count, params)

    def __len__(self) -> int:
        return len(self.count)

    def poses(self, t: float) -> np.ndarray:
        """(K, 4): x, y, z, yaw of every aircraft at time t."""
        out = np.zeros((len(self), 4))
        for k in range(len(self)):
            out[k] = aircraft_pose(self.waypoints, self.cumlen, self.count, self.params, k, t)
        return out

    def boxes(self, t: float) -> np.ndarray:
        """(K, 8) box parameters (cx, cy, cz, hx, hy, hz, cos yaw, sin yaw) at time t."""
        p = self.poses(t)
        return np.column_stack(
            [p[:, :3], self.params[:, 3:6], np.cos(p[:, 3]), np.sin(p[:, 3])]
        ) if len(self) else np.zeros((0, 8))

    def bounding_radius(self) -> np.ndarray:
        """(K,) radius of the sphere that holds each box."""
        return np.linalg.norm(self.params[:, 3:6], axis=1)


@nb.njit(cache=True, nogil=True)
def aircraft_pose(wps: np.ndarray, cum: np.ndarray, count: np.ndarray, params: np.ndarray,
                  k: int, t: float) -> tuple[float, float, float, float]:
    """Position and yaw of aircraft k at time t (constant speed around the loop)."""
    total = params[k, 2]
    n = count[k]
    if total <= 0.0:
        return wps[k, 0, 0], wps[k, 0, 1], wps[k, 0, 2], 0.0
    s = (params[k, 1] + params[k, 0] * t) % total
    i = 0
    while i < n - 2 and cum[k, i + 1] <= s:
        i += 1
    seg = cum[k, i + 1] - cum[k, i]
    f = (s - cum[k, i]) / seg if seg > 0.0 else 0.0
    dx = wps[k, i + 1, 0] - wps[k, i, 0]
    dy = wps[k, i + 1, 1] - wps[k, i, 1]
    x = wps[k, i, 0] + f * dx
    y = wps[k, i, 1] + f * dy
    z = wps[k, i, 2] + f * (wps[k, i + 1, 2] - wps[k, i, 2])
    yaw = math.atan2(dy, dx) if dx != 0.0 or dy != 0.0 else 0.0
    return x, y, z, yaw


def box_planes(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half-spaces (6K,4), plane start offsets (K+1,) and bounding spheres (K,4) of boxes."""
    k = len(boxes)
    planes = np.zeros((6 * k, 4))
    for i, (cx, cy, cz, hx, hy, hz, c, s) in enumerate(boxes):
        normals = np.array([[0, 0, -1], [0, 0, 1], [s, -c, 0], [-s, c, 0],
                            [-c, -s, 0], [c, s, 0]], float)
        ext = np.array([hz, hz, hy, hy, hx, hx])
        planes[6 * i : 6 * i + 6, :3] = normals
        planes[6 * i : 6 * i + 6, 3] = normals @ np.array([cx, cy, cz]) + ext
    start = np.arange(k + 1, dtype=np.int64) * 6
    spheres = np.column_stack([boxes[:, :3], np.linalg.norm(boxes[:, 3:6], axis=1) + 1e-6]) \
        if k else np.zeros((0, 4))
    return planes, start, spheres
