"""Static obstacles as convex solids: city buildings (boxes) and trees (prisms, frusta).

Every solid is one convex polyhedron given twice, consistently: as a triangle mesh
(for Embree and the renderer) and as outward half-spaces ``n . x <= d`` (for the
numba ray caster and collision). A tree is two solids: a prism trunk and a
pyramid-frustum crown.

Collision of a sphere with a solid: exact for boxes (clamp in the box frame); for
other solids the sphere collides when ``max_i (n_i . p - d_i) < r``, which is exact
on faces and conservative within ``r (1/cos(a/2) - 1)`` of an edge of dihedral
exterior angle ``a`` (at most 0.12 m for r = 0.3 m and the 45 degree edges of an
octagonal crown).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sitl.world.scenario import BuildingsConfig, TreesConfig
from sitl.world.terrain import Heightfield


@dataclass
class ConvexSolid:
    """A convex polyhedron: mesh, half-spaces and (for boxes) the box parameters."""

    vertices: np.ndarray  # (V,3) float64
    triangles: np.ndarray  # (T,3) int32, outward winding
    planes: np.ndarray  # (F,4): unit outward normal n and offset d, inside: n.x <= d
    kind: str  # "building", "trunk", "crown"
    box: np.ndarray | None = None  # (8,) cx, cy, cz, hx, hy, hz, cos(yaw), sin(yaw)


def box_solid(center: np.ndarray, half: np.ndarray, yaw: float = 0.0, kind: str = "building"
              ) -> ConvexSolid:
    """A box of half-extents ``half`` (x along the yawed axis), centred at ``center``."""
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    signs = np.array([[sx, sy, sz] for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)], float)
    verts = np.asarray(center, float) + (signs * half) @ rot.T
    # vertex index = ix + 2 iy + 4 iz ; two triangles per face, outward winding
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = np.array([t for q in quads for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))], np.int32)
    normals = np.array([[0, 0, -1], [0, 0, 1], [0, -1, 0], [0, 1, 0], [-1, 0, 0], [1, 0, 0]], float)
    normals = normals @ rot.T
    extents = np.array([half[2], half[2], half[1], half[1], half[0], half[0]], float)
    d = normals @ np.asarray(center, float) + extents
    box = np.array([*center, *half, c, s], float)
    return ConvexSolid(verts, tris, np.column_stack([normals, d]), kind, box)


def frustum_solid(cx: float, cy: float, z0: float, z1: float, r0: float, r1: float,
                  sides: int, kind: str) -> ConvexSolid:
    """A regular ``sides``-gon frustum, circumradius r0 at z0 and r1 (> 0) at z1."""
    ang = 2 * math.pi * np.arange(sides) / sides
    ring = np.column_stack([np.cos(ang), np.sin(ang)])
    bottom = np.column_stack([cx + r0 * ring[:, 0], cy + r0 * ring[:, 1], np.full(sides, z0)])
    top = np.column_stack([cx + r1 * ring[:, 0], cy + r1 * ring[:, 1], np.full(sides, z1)])
    verts = np.vstack([bottom, top])
    tris: list[tuple[int, int, int]] = []
    planes: list[np.ndarray] = []
    for i in range(sides):
        j = (i + 1) % sides
        tris += [(i, j, sides + j), (i, sides + j, sides + i)]
        n = np.cross(verts[j] - verts[i], verts[sides + i] - verts[i])
        n /= np.linalg.norm(n)
        if n[:2] @ (verts[i, :2] - (cx, cy)) < 0:
            n = -n
        planes.append(np.array([*n, n @ verts[i]]))
    for i in range(1, sides - 1):
        tris += [(0, i + 1, i), (sides, sides + i, sides + i + 1)]
    planes += [np.array([0.0, 0.0, -1.0, -z0]), np.array([0.0, 0.0, 1.0, z1])]
    return ConvexSolid(verts, np.array(tris, np.int32), np.array(planes), kind)


def generate_buildings(cfg: BuildingsConfig, bounds: tuple[float, float, float, float],
                       terrain: Heightfield, rng: np.random.Generator) -> list[ConvexSolid]:
    """Boxes on a grid of blocks (pitch ``block``) inside ``bounds``.

    Each block holds a building with probability ``fill``; its footprint leaves at
    least ``street`` metres to the neighbouring blocks, so the streets stay a
    connected network and every building can be flown around.
    """
    if cfg.fill <= 0:
        return []
    xmin, xmax, ymin, ymax = bounds
    nbx = max(1, int((xmax - xmin) // cfg.block))
    nby = max(1, int((ymax - ymin) // cfg.block))
    ox = xmin + (xmax - xmin - nbx * cfg.block) / 2
    oy = ymin + (ymax - ymin - nby * cfg.block) / 2
    max_side = cfg.block - cfg.street
    out = []
    for j in range(nby):
        for i in range(nbx):
            if rng.uniform() >= cfg.fill:
                continue
            sx, sy = rng.uniform(cfg.min_size, max_side, size=2)
            cx = ox + (i + 0.5) * cfg.block + rng.uniform(-1, 1) * (max_side - sx) / 2
            cy = oy + (j + 0.5) * cfg.block + rng.uniform(-1, 1) * (max_side - sy) / 2
            xs, ys = np.meshgrid(np.linspace(cx - sx / 2, cx + sx / 2, 5),
                                 np.linspace(cy - sy / 2, cy + sy / 2, 5))
            hs = terrain.height(xs, ys)
            base = float(np.min(hs)) - 0.2
            top = float(np.max(hs)) + rng.uniform(*cfg.height)
            half = np.array([sx / 2, sy / 2, (top - base) / 2])
            out.append(box_solid(np.array([cx, cy, (top + base) / 2]), half))
    return out


def generate_trees(cfg: TreesConfig, extent: tuple[float, float, float, float],
                   terrain: Heightfield, rng: np.random.Generator) -> list[ConvexSolid]:
    """Trees at random positions in ``extent`` keeping ``min_gap`` between crowns."""
    xmin, xmax, ymin, ymax = extent
    placed: list[tuple[float, float, float]] = []  # x, y, crown radius
    out: list[ConvexSolid] = []
    attempts = 0
    while len(placed) < cfg.count and attempts < 200 * max(cfg.count, 1):
        attempts += 1
        x, y = rng.uniform(xmin, xmax), rng.uniform(ymin, ymax)
        rc = rng.uniform(*cfg.crown_radius)
        if any((x - px) ** 2 + (y - py) ** 2 < (rc + pr + cfg.min_gap) ** 2
               for px, py, pr in placed):
            continue
        placed.append((x, y, rc))
        ground = float(terrain.height(x, y))
        height = rng.uniform(*cfg.height)
        crown0 = ground + min(rng.uniform(*cfg.crown_base), 0.5 * height)
        top = ground + height
        out.append(frustum_solid(x, y, ground - 0.2, crown0 + 0.05, cfg.trunk_radius,
                                 cfg.trunk_radius, cfg.sides, "trunk"))
        out.append(frustum_solid(x, y, crown0, top, rc, 0.08 * rc, cfg.sides, "crown"))
    return out


@dataclass
class PackedSolids:
    """Solids as flat arrays for the numba kernels."""

    planes: np.ndarray  # (P,4) all half-spaces
    start: np.ndarray  # (M+1,) int64: solid m owns planes[start[m]:start[m+1]]
    aabb: np.ndarray  # (M,6) xmin, ymin, zmin, xmax, ymax, zmax
    sphere: np.ndarray  # (M,4) bounding sphere cx, cy, cz, r
    box: np.ndarray  # (M,8) box parameters, hx = 0 when the solid is not a box


def pack_solids(solids: list[ConvexSolid]) -> PackedSolids:
    """Flatten ``solids`` for the kernels (empty arrays of the right shape if none)."""
    m = len(solids)
    planes = np.concatenate([s.planes for s in solids]) if m else np.zeros((0, 4))
    counts = np.array([len(s.planes) for s in solids], np.int64)
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    aabb = np.zeros((m, 6))
    sphere = np.zeros((m, 4))
    box = np.zeros((m, 8))
    for i, s in enumerate(solids):
        lo, hi = s.vertices.min(0), s.vertices.max(0)
        aabb[i] = [*lo, *hi]
        c = (lo + hi) / 2
        sphere[i] = [*c, np.linalg.norm(s.vertices - c, axis=1).max() + 1e-6]
        if s.box is not None:
            box[i] = s.box
    return PackedSolids(np.ascontiguousarray(planes, float), start, aabb, sphere, box)


def merge_meshes(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate (vertices, triangles) meshes into one (float32, int32)."""
    verts, tris, off = [], [], 0
    for v, t in parts:
        verts.append(np.asarray(v, np.float32))
        tris.append(np.asarray(t, np.int64) + off)
        off += len(v)
    if not verts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
    return np.concatenate(verts), np.concatenate(tris).astype(np.int32)
