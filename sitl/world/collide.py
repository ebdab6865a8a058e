"""Numba kernels: sphere collision with terrain, convex solids and moving aircraft.

Terrain: the sphere collides when the terrain under its centre reaches its lowest
point, or when any triangle of the cells under it is closer than the radius (exact
point-triangle distance, Ericson's closest-point test). A quick reject against the
highest vertex under the sphere skips the exact part in open air.
Solids: see ``sitl.world.obstacles`` (exact for boxes, face-plane test otherwise).
Aircraft: yawed boxes at their pose at time t, exact.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from sitl.world.aircraft import aircraft_pose

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@nb.njit(**_JIT)
def height_at(h: np.ndarray, x0: float, y0: float, res: float, x: float, y: float) -> float:
    """Mesh height at (x, y), clamped to the grid (see ``sitl.world.terrain``)."""
    nx, ny = h.shape[1] - 1, h.shape[0] - 1
    fx = min(max((x - x0) / res, 0.0), float(nx))
    fy = min(max((y - y0) / res, 0.0), float(ny))
    ix, iy = min(int(fx), nx - 1), min(int(fy), ny - 1)
    u, v = fx - ix, fy - iy
    h00, h10, h01, h11 = h[iy, ix], h[iy, ix + 1], h[iy + 1, ix], h[iy + 1, ix + 1]
    if u >= v:
        return h00 + (h10 - h00) * u + (h11 - h10) * v
    return h00 + (h11 - h01) * u + (h01 - h00) * v


@nb.njit(**_JIT)
def _dist2_point_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz) -> float:
    """Squared distance from p to triangle abc (Ericson, Real-Time Collision Detection)."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        qx, qy, qz = ax, ay, az
    else:
        bpx, bpy, bpz = px - bx, py - by, pz - bz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        cpx, cpy, cpz = px - cx, py - cy, pz - cz
        d5 = abx * cpx + aby * cpy + abz * cpz
        d6 = acx * cpx + acy * cpy + acz * cpz
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:
            qx, qy, qz = bx, by, bz
        elif d6 >= 0.0 and d5 <= d6:
            qx, qy, qz = cx, cy, cz
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            w = d1 / (d1 - d3)
            qx, qy, qz = ax + w * abx, ay + w * aby, az + w * abz
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            w = d2 / (d2 - d6)
            qx, qy, qz = ax + w * acx, ay + w * acy, az + w * acz
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            qx, qy, qz = bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz)
        else:
            den = 1.0 / (va + vb + vc)
            v = vb * den
            w = vc * den
            qx = ax + abx * v + acx * w
            qy = ay + aby * v + acy * w
            qz = az + abz * v + acz * w
    return (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2


@nb.njit(**_JIT)
def sphere_hits_terrain(h, x0, y0, res, px, py, pz, r) -> bool:
    """True if the sphere (p, r) touches or is below the terrain mesh."""
    if height_at(h, x0, y0, res, px, py) >= pz - r:
        return True
    nx, ny = h.shape[1] - 1, h.shape[0] - 1
    i0 = max(int(math.floor((px - r - x0) / res)), 0)
    i1 = min(int(math.floor((px + r - x0) / res)), nx - 1)
    j0 = max(int(math.floor((py - r - y0) / res)), 0)
    j1 = min(int(math.floor((py + r - y0) / res)), ny - 1)
    top = -np.inf
    for j in range(j0, j1 + 2):
        for i in range(i0, i1 + 2):
            top = max(top, h[min(j, ny), min(i, nx)])
    if top < pz - r:
        return False
    r2 = r * r
    for j in range(j0, j1 + 1):
        for i in range(i0, i1 + 1):
            xa, ya = x0 + i * res, y0 + j * res
            xb, yb = xa + res, ya + res
            h00, h10, h01, h11 = h[j, i], h[j, i + 1], h[j + 1, i], h[j + 1, i + 1]
            if _dist2_point_triangle(px, py, pz, xa, ya, h00, xb, ya, h10, xb, yb, h11) < r2:
                return True
            if _dist2_point_triangle(px, py, pz, xa, ya, h00, xb, yb, h11, xa, yb, h01) < r2:
                return True
    return False


@nb.njit(**_JIT)
def sphere_hits_box(px, py, pz, r, cx, cy, cz, hx, hy, hz, c, s) -> bool:
    """Exact sphere / yawed box overlap."""
    dx, dy = px - cx, py - cy
    lx = c * dx + s * dy
    ly = -s * dx + c * dy
    lz = pz - cz
    qx = lx - min(max(lx, -hx), hx)
    qy = ly - min(max(ly, -hy), hy)
    qz = lz - min(max(lz, -hz), hz)
    return qx * qx + qy * qy + qz * qz < r * r


@nb.njit(**_JIT)
def sphere_hits_solids(px, py, pz, r, planes, start, aabb, box) -> bool:
    """True if the sphere overlaps any convex solid."""
    for m in range(aabb.shape[0]):
        if (px < aabb[m, 0] - r or px > aabb[m, 3] + r or py < aabb[m, 1] - r
                or py > aabb[m, 4] + r or pz < aabb[m, 2] - r or pz > aabb[m, 5] + r):
            continue
        if box[m, 3] > 0.0:
            b = box[m]
            if sphere_hits_box(px, py, pz, r, b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]):
                return True
            continue
        smax = -np.inf
        for q in range(start[m], start[m + 1]):
            smax = max(smax, planes[q, 0] * px + planes[q, 1] * py + planes[q, 2] * pz
                       - planes[q, 3])
        if smax < r:
            return True
    return False


@nb.njit(**_JIT)
def sphere_hits_aircraft(px, py, pz, r, t, wps, cum, count, params) -> bool:
    """True if the sphere overlaps any aircraft at time t."""
    for k in range(count.shape[0]):
        x, y, z, yaw = aircraft_pose(wps, cum, count, params, k, t)
        hx, hy, hz = params[k, 3], params[k, 4], params[k, 5]
        reach = r + math.sqrt(hx * hx + hy * hy + hz * hz)
        if (px - x) ** 2 + (py - y) ** 2 + (pz - z) ** 2 > reach * reach:
            continue
        if sphere_hits_box(px, py, pz, r, x, y, z, hx, hy, hz, math.cos(yaw), math.sin(yaw)):
            return True
    return False


@nb.njit(**_JIT)
def collides_static(px, py, pz, r, h, x0, y0, res, planes, start, aabb, box) -> bool:
    """Terrain or solids."""
    if sphere_hits_terrain(h, x0, y0, res, px, py, pz, r):
        return True
    return sphere_hits_solids(px, py, pz, r, planes, start, aabb, box)


@nb.njit(**_JIT)
def collides_all(px, py, pz, r, t, h, x0, y0, res, planes, start, aabb, box,
                 wps, cum, count, params) -> bool:
    """Terrain, solids and aircraft at time t."""
    if collides_static(px, py, pz, r, h, x0, y0, res, planes, start, aabb, box):
        return True
    return sphere_hits_aircraft(px, py, pz, r, t, wps, cum, count, params)


@nb.njit(**_JIT)
def segment_blocked(a, b, r, step, h, x0, y0, res, planes, start, aabb, box) -> bool:
    """True if a sphere swept from a to b (sampled every ``step`` m) hits static geometry."""
    d = math.sqrt((b[0] - a[0]) ** 2 + (b[1] - a[1]) ** 2 + (b[2] - a[2]) ** 2)
    n = max(int(math.ceil(d / step)), 1)
    for i in range(n + 1):
        f = i / n
        if collides_static(a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]),
                           a[2] + f * (b[2] - a[2]), r, h, x0, y0, res, planes, start, aabb, box):
            return True
    return False


@nb.njit(**_JIT)
def points_collide_static(pts, r, h, x0, y0, res, planes, start, aabb, box) -> np.ndarray:
    """(N,) bool: which spheres (pts[i], r) hit static geometry."""
    out = np.zeros(pts.shape[0], np.bool_)
    for i in range(pts.shape[0]):
        out[i] = collides_static(pts[i, 0], pts[i, 1], pts[i, 2], r, h, x0, y0, res,
                                 planes, start, aabb, box)
    return out
