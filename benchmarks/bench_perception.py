"""Perception benchmark: icosahedron reduction (eq. 3.1 + 3.2) of one LiDAR scan.

Keys (milliseconds per scan, median of several repeats, one core, default backend):

- ``perception_ms_28800``: a VLP-16-like scan (16 channels -15..15 deg x 1800 azimuths)
  of a UAV 3.5 m above flat ground in a 40 m x 60 m walled yard, with a 1 m wide wall
  panel 3 m ahead: every ray returns a point, about 5 % of them inside the solid.
- ``perception_ms_28800_all_inside``: worst case, all 28,800 points inside the 4 m
  sphere (uniform in the ball: most near the surface, where the 32-plane test runs).
- ``perception_ms_300000``: the same scene at 18,750 azimuths (300,000 points, the
  paper's "~300,000 points/second").

``peers`` holds the same numbers for the vectorized numpy backend, measured side by
side. Budget (DESIGN.md): 0.3 ms for one scan.
"""

from __future__ import annotations

import json
import statistics
import sys
import time

import numpy as np

from perception.faces import reduce_points
from perception.icosahedron import TruncatedIcosahedron

ALTITUDE = 3.5  # m above the ground
WALL_X, WALL_HALF_WIDTH, WALL_TOP = 3.0, 0.5, 1.5  # panel ahead, sensor frame
YARD_X, YARD_Y = 20.0, 30.0  # half extents of the surrounding walls


def vlp16_scene(n_azimuth: int = 1800, seed: int = 0, noise: float = 0.03) -> np.ndarray:
    """(16 * n_azimuth, 3) float32 points, sensor frame (FLU), ray-cast analytically."""
    el = np.deg2rad(np.linspace(-15.0, 15.0, 16))
    az = np.deg2rad(np.arange(n_azimuth) * (360.0 / n_azimuth))
    el, az = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    d = d.reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(d[:, 2] < 0, -ALTITUDE / d[:, 2], np.inf)
        t_x = np.where(d[:, 0] != 0, YARD_X / np.abs(d[:, 0]), np.inf)
        t_y = np.where(d[:, 1] != 0, YARD_Y / np.abs(d[:, 1]), np.inf)
        t_wall = np.where(d[:, 0] > 0, WALL_X / d[:, 0], np.inf)
    hit = d * t_wall[:, None]
    on_panel = (np.abs(hit[:, 1]) <= WALL_HALF_WIDTH) & (hit[:, 2] >= -ALTITUDE) & (
        hit[:, 2] <= WALL_TOP
    )
    t_wall = np.where(on_panel, t_wall, np.inf)
    t = np.minimum.reduce([t_ground, t_x, t_y, t_wall])
    t = t + np.random.default_rng(seed).normal(0.0, noise, size=t.shape)
    return (d * t[:, None]).astype(np.float32)


def all_inside(n: int = 28_800, seed: int = 0, radius: float = 4.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = radius * rng.random(n) ** (1.0 / 3.0)
    return (d * r[:, None]).astype(np.float32)


def time_ms(points: np.ndarray, ico: TruncatedIcosahedron, backend: str, repeats: int) -> float:
    reduce_points(points, ico, backend=backend)  # warm-up (numba compile / cache load)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        reduce_points(points, ico, backend=backend)
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def run(quick: bool) -> dict:
    repeats = 30 if quick else 300
    ico = TruncatedIcosahedron(4.0)
    scans = {
        "perception_ms_28800": vlp16_scene(1800),
        "perception_ms_28800_all_inside": all_inside(28_800),
        "perception_ms_300000": vlp16_scene(18_750),
    }
    result: dict = {}
    peers: dict = {}
    for key, pts in scans.items():
        reps = max(5, repeats // 10) if len(pts) > 100_000 else repeats
        result[key] = time_ms(pts, ico, "auto", reps)
        peers[f"numpy_{key}"] = time_ms(pts, ico, "numpy", max(5, reps // 3))
    scan = scans["perception_ms_28800"]
    result["perception_inside_fraction_28800"] = reduce_points(scan, ico).n_inside / len(scan)
    result["peers"] = peers
    return result


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    res = run(quick)
    peers = res.pop("peers")
    width = max(map(len, list(res) + list(peers)))
    for key, val in {**res, **peers}.items():
        print(f"{key:<{width}}  {val:10.4f}")
    if "--json" in argv:
        path = argv[argv.index("--json") + 1]
        with open(path, "w") as fh:
            json.dump({**res, "peers": peers}, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
