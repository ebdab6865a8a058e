"""Terrain: a regular-grid heightfield, generated procedurally from a seeded RNG.

The surface is the triangle mesh of the grid: every cell (ix, iy) is split along the
diagonal from its (ix, iy) corner to its (ix+1, iy+1) corner into triangle A
(v00, v10, v11; local fx >= fy) and triangle B (v00, v11, v01; fx < fy). Height
queries, collision and the numba ray marcher all use exactly these triangles, so they
agree with the Embree mesh to float precision.

Features (heights combined by maximum, then a gentle undulation added):
- hill: ``H exp(-r^2 / (2 s^2))`` with s the configured "radius";
- ridge: the same profile across the distance to a straight segment (rounded ends);
- undulation: three seeded plane waves of wavelength ~``roughness_wavelength``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from sitl.world.scenario import TerrainConfig


@dataclass
class Heightfield:
    """Vertex heights ``heights[iy, ix]`` at ``(x0 + ix*res, y0 + iy*res)``."""

    x0: float
    y0: float
    res: float
    heights: np.ndarray  # (ny+1, nx+1) float64

    @property
    def nx(self) -> int:
        return self.heights.shape[1] - 1

    @property
    def ny(self) -> int:
        return self.heights.shape[0] - 1

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) covered by the grid."""
        return (self.x0, self.x0 + self.nx * self.res, self.y0, self.y0 + self.ny * self.res)

    def height(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray | float:
        """Surface height at (x, y) on the triangle mesh; clamped to the grid's edge."""
        if np.isscalar(x) and np.isscalar(y):  # the same arithmetic on Python floats:
            return self._height_at(float(x), float(y))  # ~10x faster for one point
        fx = np.clip((np.asarray(x, dtype=float) - self.x0) / self.res, 0.0, self.nx)
        fy = np.clip((np.asarray(y, dtype=float) - self.y0) / self.res, 0.0, self.ny)
        ix = np.minimum(np.floor(fx).astype(np.int64), self.nx - 1)
        iy = np.minimum(np.floor(fy).astype(np.int64), self.ny - 1)
        u, v = fx - ix, fy - iy
        h = self.heights
        h00, h10 = h[iy, ix], h[iy, ix + 1]
        h01, h11 = h[iy + 1, ix], h[iy + 1, ix + 1]
        a = h00 + (h10 - h00) * u + (h11 - h10) * v  # triangle A (u >= v)
        b = h00 + (h11 - h01) * u + (h01 - h00) * v  # triangle B (u < v)
        return np.where(u >= v, a, b)

    def _height_at(self, x: float, y: float) -> float:
        """:meth:`height` of one point, operation for operation (bit-identical)."""
        nx, ny = self.nx, self.ny
        fx = min(max((x - self.x0) / self.res, 0.0), float(nx))
        fy = min(max((y - self.y0) / self.res, 0.0), float(ny))
        ix, iy = min(math.floor(fx), nx - 1), min(math.floor(fy), ny - 1)
        u, v = fx - ix, fy - iy
        h = self.heights
        h00, h10 = h.item(iy, ix), h.item(iy, ix + 1)
        h01, h11 = h.item(iy + 1, ix), h.item(iy + 1, ix + 1)
        if u >= v:
            return h00 + (h10 - h00) * u + (h11 - h10) * v  # triangle A
        return h00 + (h11 - h01) * u + (h01 - h00) * v  # triangle B

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (V,3) float32 and triangles (T,3) int32 of the grid's triangle mesh."""
        ny1, nx1 = self.heights.shape
        xs = self.x0 + np.arange(nx1) * self.res
        ys = self.y0 + np.arange(ny1) * self.res
        gx, gy = np.meshgrid(xs, ys)
        verts = np.stack([gx.ravel(), gy.ravel(), self.heights.ravel()], axis=1)
        idx = np.arange(ny1 * nx1, dtype=np.int32).reshape(ny1, nx1)
        v00, v10 = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        v01, v11 = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        tris = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
        return verts.astype(np.float32), tris.astype(np.int32)

    def tile_max(self, tile: int) -> np.ndarray:
        """Max vertex height per block of ``tile`` x ``tile`` cells: (ceil(ny/t), ceil(nx/t))."""
        return self._tile_reduce(tile, np.maximum)

    def tile_min(self, tile: int) -> np.ndarray:
        """Min vertex height per block of ``tile`` x ``tile`` cells."""
        return self._tile_reduce(tile, np.minimum)

    def cell_max(self) -> np.ndarray:
        """Max of the four vertex heights of every cell: (ny, nx)."""
        h = self.heights
        return np.maximum(np.maximum(h[:-1, :-1], h[:-1, 1:]), np.maximum(h[1:, :-1], h[1:, 1:]))

    def _tile_reduce(self, tile: int, fn: Callable[..., np.ndarray]) -> np.ndarray:
        h = self.heights
        cells = fn(fn(h[:-1, :-1], h[:-1, 1:]), fn(h[1:, :-1], h[1:, 1:]))  # per cell
        ty, tx = -(-self.ny // tile), -(-self.nx // tile)
        pad = -np.inf if fn is np.maximum else np.inf
        full = np.full((ty * tile, tx * tile), pad)
        full[: self.ny, : self.nx] = cells
        blocks = full.reshape(ty, tile, tx, tile)
        return (blocks.max(axis=(1, 3)) if fn is np.maximum else blocks.min(axis=(1, 3)))


def generate_terrain(
    cfg: TerrainConfig,
    extent: tuple[float, float, float, float],
    rng: np.random.Generator,
    features: tuple[float, float, float, float] | None = None,
) -> Heightfield:
    """Seeded procedural terrain over ``extent`` (xmin, xmax, ymin, ymax).

    Hill and ridge centres are drawn inside ``features`` (default: ``extent``), the
    navigable area, so that they matter for navigation.
    """
    xmin, xmax, ymin, ymax = extent
    fxmin, fxmax, fymin, fymax = features or extent
    res = cfg.resolution
    nx = max(1, math.ceil((xmax - xmin) / res - 1e-9))
    ny = max(1, math.ceil((ymax - ymin) / res - 1e-9))
    gx, gy = np.meshgrid(xmin + np.arange(nx + 1) * res, ymin + np.arange(ny + 1) * res)
    feat = np.zeros_like(gx)

    hills = cfg.hills
    for _ in range(hills.count):
        cx, cy = rng.uniform(fxmin, fxmax), rng.uniform(fymin, fymax)
        height, sigma = rng.uniform(*hills.height), rng.uniform(*hills.radius)
        r2 = (gx - cx) ** 2 + (gy - cy) ** 2
        np.maximum(feat, height * np.exp(-r2 / (2 * sigma**2)), out=feat)

    ridges = cfg.ridges
    for _ in range(ridges.count):
        cx, cy = rng.uniform(fxmin, fxmax), rng.uniform(fymin, fymax)
        ang = rng.uniform(0, math.pi)
        length, height = rng.uniform(*ridges.length), rng.uniform(*ridges.height)
        sigma = rng.uniform(*ridges.width)
        d2 = _segment_dist2(gx, gy, cx, cy, ang, length)
        np.maximum(feat, height * np.exp(-d2 / (2 * sigma**2)), out=feat)

    if cfg.roughness > 0:
        und = np.zeros_like(gx)
        for _ in range(3):
            ang = rng.uniform(0, 2 * math.pi)
            lam = cfg.roughness_wavelength * rng.uniform(0.7, 1.4)
            phase = rng.uniform(0, 2 * math.pi)
            k = 2 * math.pi / lam
            und += np.sin(k * (gx * math.cos(ang) + gy * math.sin(ang)) + phase)
        feat += cfg.roughness * und / 3.0
    return Heightfield(x0=xmin, y0=ymin, res=res, heights=feat)


def _segment_dist2(
    gx: np.ndarray, gy: np.ndarray, cx: float, cy: float, ang: float, length: float
) -> np.ndarray:
    """Squared distance of grid points to the segment of ``length`` centred at (cx, cy)."""
    ux, uy = math.cos(ang), math.sin(ang)
    dx, dy = gx - cx, gy - cy
    s = np.clip(dx * ux + dy * uy, -length / 2, length / 2)
    return (dx - s * ux) ** 2 + (dy - s * uy) ** 2
