"""LiDAR benchmark: VLP-16 scans (28,800 rays) in the valley, ours vs Open3D and plain Embree.

Poses: the UAV at the flight level (3.5 m) at episode start/goal spots of the valley
(``World.sample_start_goal``), random yaw, roll and pitch uniform in +-5 degrees.
A second, harder set ("approach") follows straight lines from start towards goal
until the body would hit a hill, one pose a metre: most of those scans look at a
hillside close by.

Keys (rays/s = 28,800 / time per scan; time per scan = CPU time of this process for
one pass over all poses / number of poses; median of several passes; one core):

- ``lidar_rays_per_s``: ``Lidar.scan`` at full range (100 m), default engine.
- ``lidar_rays_per_s_truncated``: ``Lidar.scan`` at max_range 4.5 m (the env's).
- ``lidar_ms_per_scan[_truncated]``, ``lidar_ms_per_scan_truncated_approach``: the same
  as milliseconds per scan (budget in DESIGN.md: 3 ms full, 0.5 ms truncated).
- ``lidar_rays_per_s_<engine>[_truncated]``: each of our two engines (``embree``,
  ``numba``) forced, which is how the default ("auto") was chosen.
- ``peers``: ``open3d_rays_per_s`` (Open3D ``RaycastingScene.cast_rays``, one thread,
  same triangle mesh, rays built from the pose each scan; it has no maximum range, so
  the truncated peer number is the same cast then filtered) and
  ``embreex_plain_rays_per_s`` (embreex ``EmbreeScene.run`` on all 28,800 rays, no
  culling, distances only). Open3D is optional (``pip install open3d``; it needs the
  system library libusb-1.0); without it the peer is reported as skipped.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable

import numpy as np

from sitl.lidar.scanner import Lidar, LidarConfig
from sitl.world.world import UAV_BODY_RADIUS, World

N_RAYS = 28_800


def rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Body FLU -> world ENU for Z-Y-X Euler angles."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def _tilt(rng: np.random.Generator, yaw: float) -> np.ndarray:
    tilt = math.radians(5.0)
    return rotation(yaw, rng.uniform(-tilt, tilt), rng.uniform(-tilt, tilt))


def open_poses(world: World, n: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Start/goal spots at the flight level, random yaw, small tilt."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        for p in world.sample_start_goal(rng):
            out.append((p, _tilt(rng, rng.uniform(-math.pi, math.pi))))
    return out[:n]


def approach_poses(world: World, n: int, seed: int = 1) -> list[tuple[np.ndarray, np.ndarray]]:
    """Along straight start -> goal lines until the body would collide, 1 m apart."""
    rng = np.random.default_rng(seed)
    out: list[tuple[np.ndarray, np.ndarray]] = []
    while len(out) < n:
        s, g = world.sample_start_goal(rng)
        d = (g - s) / np.linalg.norm(g - s)
        for k in range(int(np.linalg.norm(g - s))):
            p = s + d * k
            if world.collides_static(p, UAV_BODY_RADIUS):
                break
            out.append((p, _tilt(rng, math.atan2(d[1], d[0]) + rng.normal(0, 0.3))))
    return out[:n]


def time_per_scan(fn: Callable[[np.ndarray, np.ndarray], object],
                  poses: list[tuple[np.ndarray, np.ndarray]], repeats: int) -> float:
    """Median over passes of the CPU seconds per scan."""
    fn(*poses[0])  # warm-up (JIT, lazy scene builds)
    times = []
    for _ in range(repeats):
        t0 = time.process_time()
        for p, r in poses:
            fn(p, r)
        times.append((time.process_time() - t0) / len(poses))
    return statistics.median(times)


def _lidar_scan(world: World, max_range: float, engine: str = "auto") -> Callable:
    lidar = Lidar(world, LidarConfig(max_range=max_range, engine=engine))
    return lambda p, r: lidar.scan(p, r, 0.0)


def _world_rays(lidar: Lidar, p: np.ndarray, r: np.ndarray) -> np.ndarray:
    rays = np.empty((lidar.n_rays, 6), np.float32)
    rays[:, :3] = p
    rays[:, 3:] = lidar.dirs @ r.T
    return rays


def embree_plain(world: World) -> Callable:
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    verts, tris = world.static_mesh()
    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, verts, tris)
    lidar = Lidar(world)

    def cast(p: np.ndarray, r: np.ndarray) -> np.ndarray:
        rays = _world_rays(lidar, p, r)
        return scene.run(rays[:, :3], rays[:, 3:], query="DISTANCE")

    return cast


def open3d_cast(world: World, max_range: float) -> Callable | str:
    try:
        import open3d as o3d
    except Exception as exc:  # optional peer: any import failure (e.g. libusb) skips it
        return f"skipped: open3d unavailable ({type(exc).__name__}: {exc})"
    verts, tris = world.static_mesh()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(tris.astype(np.uint32)))
    lidar = Lidar(world)

    def cast(p: np.ndarray, r: np.ndarray) -> np.ndarray:
        rays = o3d.core.Tensor(_world_rays(lidar, p, r))
        t = scene.cast_rays(rays, nthreads=1)["t_hit"].numpy()
        return t[t <= max_range]

    return cast


def rate(seconds_per_scan: float) -> float:
    return N_RAYS / seconds_per_scan


def run(quick: bool) -> dict:
    n_poses, repeats = (12, 3) if quick else (100, 5)
    world = World("valley")
    poses = open_poses(world, n_poses)
    approach = approach_poses(world, n_poses)

    full = time_per_scan(_lidar_scan(world, 100.0), poses, repeats)
    short = time_per_scan(_lidar_scan(world, 4.5), poses, repeats)
    short_approach = time_per_scan(_lidar_scan(world, 4.5), approach, repeats)
    out: dict = {
        "lidar_rays_per_s": rate(full),
        "lidar_rays_per_s_truncated": rate(short),
        "lidar_ms_per_scan": full * 1e3,
        "lidar_ms_per_scan_truncated": short * 1e3,
        "lidar_ms_per_scan_truncated_approach": short_approach * 1e3,
    }
    for engine in ("embree", "numba"):
        for max_range, suffix in ((100.0, ""), (4.5, "_truncated")):
            s = time_per_scan(_lidar_scan(world, max_range, engine), poses, repeats)
            out[f"lidar_rays_per_s_{engine}{suffix}"] = rate(s)

    peers: dict = {"embreex_plain_rays_per_s": rate(time_per_scan(embree_plain(world), poses,
                                                                  repeats))}
    o3d_full = open3d_cast(world, 100.0)
    if isinstance(o3d_full, str):
        peers["open3d_rays_per_s"] = None
        peers["open3d_note"] = o3d_full
    else:
        peers["open3d_rays_per_s"] = rate(time_per_scan(o3d_full, poses, repeats))
        o3d_short = open3d_cast(world, 4.5)
        peers["open3d_rays_per_s_truncated"] = rate(time_per_scan(o3d_short, poses, repeats))
    out["peers"] = peers
    return out


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(run(quick="--quick" in sys.argv), indent=2))
