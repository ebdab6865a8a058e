"""Velodyne VLP-16 simulation: 16 channels, 360 degrees, hits only, in the sensor frame.

Ray grid: 16 channels from -15 to +15 degrees (2 degrees apart) and an azimuth step
of 0.2 degrees, which is the VLP-16's firing cycle (55.296 us) at 10 Hz rotation
(360 x 10 x 55.296e-6 = 0.199 deg): 1800 x 16 = 28,800 rays a scan. Ray ``i`` has
azimuth column ``i // 16`` (0 = sensor +x, counter-clockwise) and channel ``i % 16``.

Ranges: surfaces closer than ``min_range`` (0.9 m) or farther than ``max_range``
(100 m) give no return; a nearer surface still occludes. Gaussian range noise (sigma
0.03 m, seeded) is added to each return's range before the range limits apply.

Simplification: the whole scan is taken at the single time ``t`` (a real VLP-16
sweeps over 0.1 s); moving aircraft appear where they are at ``t``.

Culling first (``sitl.lidar.raycull``): for short ranges (the 4.5 m sensing radius) a
per-column horizon built from 0.5 m terrain tiles near the sensor selects the rays that
can hit anything and where their march may start; in open air nothing is cast. For
long ranges only rays that climb away from everything are skipped.

Engines (``LidarConfig.engine``), chosen by ``benchmarks/bench_lidar.py`` (valley, one
core, this machine: full range ~6.2 M rays/s Embree vs ~5 M numba; 4.5 m range
~34-42 M rays/s numba vs ~26 M Embree, i.e. ~0.7 ms vs ~1.1 ms a scan):
- ``"embree"``: static geometry (terrain + obstacles) as one triangle mesh in Embree
  (embreex ``EmbreeScene.run``, distances only) on the culled rays;
- ``"numba"``: the heightfield marcher + splatted convex solids (``sitl.lidar.raycast``) on
  the same triangles: both engines agree to float precision (tested);
- ``"auto"`` (default): Embree above ``AUTO_EMBREE_ABOVE`` (20 m) max range, numba at
  or below it. Aircraft are always splatted analytically (numba) and merged by
  minimum range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from sitl.lidar import raycast, raycull
from sitl.world.aircraft import box_planes
from sitl.world.world import World

TILE = 8  # cells per marcher tile (2 m at 0.25 m resolution)
HORIZON_TILE = 2  # cells per horizon-cull tile (0.5 m)
HORIZON_BELOW = 20.0  # m: for max_range up to this, cull rays by the local horizon
AUTO_EMBREE_ABOVE = 20.0  # m: "auto" uses Embree for max_range above this, numba below


@dataclass
class LidarConfig:
    """VLP-16 parameters (defaults: the datasheet's)."""

    channels: int = 16
    min_elevation_deg: float = -15.0
    max_elevation_deg: float = 15.0
    rotation_hz: float = 10.0
    azimuth_step_deg: float = 0.2  # 360 deg * rotation_hz * 55.296 us firing cycle
    min_range: float = 0.9
    max_range: float = 100.0
    noise_sigma: float = 0.03
    engine: str = "auto"  # "auto" | "embree" | "numba"

    def __post_init__(self) -> None:
        if self.channels < 1:
            raise ValueError(f"channels must be >= 1, got {self.channels}")
        if not -90 <= self.min_elevation_deg <= self.max_elevation_deg <= 90:
            raise ValueError("elevations must satisfy -90 <= min <= max <= 90")
        if not 0 < self.azimuth_step_deg <= 360:
            raise ValueError(f"azimuth_step_deg must be in (0, 360], got {self.azimuth_step_deg}")
        if not 0 <= self.min_range < self.max_range:
            raise ValueError("ranges must satisfy 0 <= min_range < max_range")
        if self.noise_sigma < 0:
            raise ValueError(f"noise_sigma must be >= 0, got {self.noise_sigma}")
        if self.engine not in ("auto", "embree", "numba"):
            raise ValueError(f"engine must be auto, embree or numba, got {self.engine!r}")


def ray_grid(config: LidarConfig) -> tuple[np.ndarray, np.ndarray]:
    """Sensor-frame unit directions (N,3) and the grid descriptor for the kernels."""
    ncol = int(round(360.0 / config.azimuth_step_deg))
    daz = 2 * math.pi / ncol
    el0 = math.radians(config.min_elevation_deg)
    dele = (math.radians(config.max_elevation_deg) - el0) / max(config.channels - 1, 1)
    az = np.arange(ncol) * daz
    el = el0 + np.arange(config.channels) * dele
    a, e = np.meshgrid(az, el, indexing="ij")
    dirs = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1)
    grid = np.array([ncol, config.channels, 0.0, daz, el0, dele])
    return np.ascontiguousarray(dirs.reshape(-1, 3)), grid


class Lidar:
    """A VLP-16 in a :class:`World`; ``scan`` returns the hit points of one revolution."""

    def __init__(self, world: World, config: LidarConfig | None = None, seed: int = 0) -> None:
        self.world = world
        self.config = config or LidarConfig()
        self.dirs, self.grid = ray_grid(self.config)
        self.n_rays: int = len(self.dirs)
        t = world.terrain
        h = t.heights
        cmax = t.cell_max()
        self._terrain = (h, np.ascontiguousarray(cmax), t.x0, t.y0, t.res, t.tile_max(TILE), TILE)
        p = world.packed
        tops = [float(t.heights.max())] + ([float(p.aabb[:, 5].max())] if len(p.aabb) else [])
        self._gmax_terrain = float(t.heights.max())
        self._horizon = (t.tile_max(HORIZON_TILE), t.tile_min(HORIZON_TILE),
                         HORIZON_TILE * t.res)
        self._hz = np.empty(int(self.grid[0]))
        self._colmin = np.zeros(int(self.grid[0]))  # march start per column
        self._top_all = max(tops)
        self._dist = np.empty(self.n_rays)
        self._zeros = np.zeros(self.n_rays)
        self._idx = np.empty(self.n_rays, np.int64)
        self._embree = None
        self._org32 = np.empty((self.n_rays, 3), np.float32)
        self._dir32 = np.empty((self.n_rays, 3), np.float32)
        self.engine = self._pick_engine()
        self.reseed(seed)

    def _pick_engine(self) -> str:
        if self.config.engine != "auto":
            return self.config.engine
        return "embree" if self.config.max_range > AUTO_EMBREE_ABOVE else "numba"

    def set_max_range(self, max_range: float) -> None:
        """Reach ``max_range`` from the next scan on (the rays, the world's structures and
        the noise stream are kept; the engine is chosen again for the range)."""
        self.config = replace(self.config, max_range=float(max_range))
        self.engine = self._pick_engine()

    def reseed(self, seed: int) -> None:
        """Restart the range-noise stream."""
        self._rng = np.random.default_rng(seed)

    # --- casting -----------------------------------------------------------------

    def ranges(self, position: np.ndarray, rotation: np.ndarray, t: float) -> np.ndarray:
        """(n_rays,) true distance to the first surface, ``max_range`` where none.

        No noise, no minimum range. The returned array is reused by the next call.
        """
        o = np.ascontiguousarray(position, dtype=np.float64).reshape(3)
        rot = np.ascontiguousarray(rotation, dtype=np.float64).reshape(3, 3)
        tmax = float(self.config.max_range)
        dist = self._dist
        dist.fill(tmax)
        h, cmax, x0, y0, res, tilemax, tile = self._terrain
        p = self.world.packed
        if tmax <= HORIZON_BELOW:
            hmax, hmin, hsize = self._horizon
            # the numba engine splats solids itself: only the terrain decides its rays
            spheres = p.sphere if self.engine == "embree" else p.sphere[:0]
            n = raycull.horizon_candidates(o, rot, self.grid, tmax, hmax, hmin, x0, y0, hsize,
                                           spheres, self._hz, self._colmin, self._idx)
        else:
            n = raycull.candidates(o, rot, self.dirs, tmax, self._top_all, self._idx)
            self._colmin.fill(0.0)
        if self.engine == "embree":
            self._cast_embree(o, rot, n, tmax)
        else:
            raycast.cast_solids(o, rot, self.dirs, self.grid, tmax, p.planes, p.start,
                                p.sphere, dist)
            raycast.cast_terrain(o, rot, self.dirs, self._idx, n, self._colmin,
                                 int(self.grid[1]), dist, h, cmax, x0, y0, res, tilemax, tile,
                                 self._gmax_terrain)
        if len(self.world.fleet):
            planes, start, spheres = box_planes(self.world.aircraft_boxes(t))
            raycast.cast_solids(o, rot, self.dirs, self.grid, tmax, planes, start, spheres,
                                dist)
        return dist

    def _cast_embree(self, o: np.ndarray, rot: np.ndarray, n: int, tmax: float) -> None:
        if n == 0:
            return
        scene = self._embree_scene()
        org, dirs = self._org32[:n], self._dir32[:n]
        org[:] = o.astype(np.float32)
        raycast.world_dirs_idx(rot, self.dirs, self._idx, n, dirs)
        cutoff = np.float32(tmax)
        d = scene.run(org, dirs, dists=float(cutoff), query="DISTANCE")
        raycast.scatter(self._idx, n, d, float(cutoff), self._dist)

    def _embree_scene(self) -> object:
        if self._embree is None:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh

            verts, tris = self.world.static_mesh()
            scene = rtcore_scene.EmbreeScene()
            TriangleMesh(scene, verts, tris)
            self._embree = scene
        return self._embree

    def scan(self, position: np.ndarray, rotation: np.ndarray, t: float) -> np.ndarray:
        """Hit points (N,3) float32 in the sensor frame (body FLU at ``position``)."""
        return self.scan_rings(position, rotation, t)[0]

    def scan_rings(self, position: np.ndarray, rotation: np.ndarray,
                   t: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`scan` and each return's ring ((N,) uint16, the laser's channel, 0 = the
        lowest beam: what ``bus.messages.elevation_rings`` finds from the point, known
        here from the ray without it)."""
        cfg = self.config
        dist = self.ranges(position, rotation, t)
        n = raycast.gather_hits(dist, cfg.max_range, self._idx)
        sigma = cfg.noise_sigma
        noise = self._rng.standard_normal(n) if sigma > 0 else self._zeros[:n]
        out = np.empty((n, 3), np.float32)
        rings = np.empty(n, np.uint16)
        m = raycast.make_points(dist, self._idx, n, noise, sigma, cfg.min_range, cfg.max_range,
                                self.dirs, cfg.channels, out, rings)
        return out[:m], rings[:m]
