"""Numba ray-casting kernels for a spinning LiDAR's regular ray grid.

Rays are given in the sensor frame as a regular grid: index ``i = col * nch + ch``,
azimuth ``az0 + col * daz``, elevation ``el0 + ch * dEl``; ``rot`` maps sensor to world
and ``o`` is the world origin. Distances are written into ``dist`` (initialised to the
maximum range by the caller) where a surface is closer.

- Terrain: a heightfield marcher (Amanatides-Woo DDA over cells, each rejected by its
  maximum height or intersected exactly with its two triangles, see ``sitl.world.terrain``)
  after clipping each ray to the grid and to the highest terrain point; long rays
  first march 2 m tiles holding their maximum height and descend only where needed.
- Convex solids (static obstacles, aircraft): "splatted" onto the ray grid. Each
  solid's bounding sphere covers a small azimuth/elevation window of the grid; only
  rays in the window are intersected with the solid's half-spaces (Cyrus-Beck).

Culling (which rays need casting at all) lives in ``sitl.lidar.raycull``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}
INF = np.inf
SHORT_TILES = 4.0  # spans up to this many tiles skip the tile level (measured faster)


@nb.njit(**_JIT)
def world_dirs_idx(rot: np.ndarray, dirs_s: np.ndarray, idx: np.ndarray, n: int,
                   out: np.ndarray) -> None:
    """out[k] = rot @ dirs_s[idx[k]] for k < n (out may be float32, for Embree)."""
    for k in range(n):
        i = idx[k]
        x, y, z = dirs_s[i, 0], dirs_s[i, 1], dirs_s[i, 2]
        out[k, 0] = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z
        out[k, 1] = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z
        out[k, 2] = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z


@nb.njit(**_JIT)
def _seg_hit(oz, dz, u0, v0, du, dv, t_s, t_e, h00, h10, h01, h11) -> float:
    """Crossing within [t_s, t_e], a span over one triangle of the cell."""
    tmid = 0.5 * (t_s + t_e)
    if u0 + du * tmid >= v0 + dv * tmid:  # triangle A
        bu, bv = h10 - h00, h11 - h10
    else:  # triangle B
        bu, bv = h11 - h01, h01 - h00
    g0 = oz + dz * t_s - (h00 + bu * (u0 + du * t_s) + bv * (v0 + dv * t_s))
    if g0 <= 0.0:
        return t_s
    g1 = oz + dz * t_e - (h00 + bu * (u0 + du * t_e) + bv * (v0 + dv * t_e))
    if g1 <= 0.0:
        return t_s + (t_e - t_s) * g0 / (g0 - g1)
    return INF


@nb.njit(**_JIT)
def _cell_hit(oz, dz, fx0, fy0, du, dv, c0, inv_dd, ta, tb, h, i, j) -> float:
    """First crossing of the ray with the two triangles of cell (i, j) within [ta, tb].

    The ray in cell units: u(t) = fx0 - i + du t, v(t) = fy0 - j + dv t; it crosses the
    cell's diagonal u = v at t = (i - j - c0) * inv_dd with c0 = fx0 - fy0.
    """
    h00, h10, h01, h11 = h[j, i], h[j, i + 1], h[j + 1, i], h[j + 1, i + 1]
    u0, v0 = fx0 - i, fy0 - j
    tm = (i - j - c0) * inv_dd
    if ta < tm < tb:
        t = _seg_hit(oz, dz, u0, v0, du, dv, ta, tm, h00, h10, h01, h11)
        if t < INF:
            return t
        return _seg_hit(oz, dz, u0, v0, du, dv, tm, tb, h00, h10, h01, h11)
    return _seg_hit(oz, dz, u0, v0, du, dv, ta, tb, h00, h10, h01, h11)


@nb.njit(inline="always", **_JIT)
def _dda_init(o, d, t, x0, size, n):
    """Start cell, step, next boundary t and boundary spacing along one axis."""
    p = o + d * t
    i = min(max(int(math.floor((p - x0) / size)), 0), n - 1)
    if d > 0.0:
        return i, 1, (x0 + (i + 1) * size - o) / d, size / d
    if d < 0.0:
        return i, -1, (x0 + i * size - o) / d, -size / d
    return i, 0, INF, INF


@nb.njit(inline="always", **_JIT)
def _march_cells(ox, oy, oz, dx, dy, dz, ta, tb, h, cmax, x0, y0, res) -> float:
    """Cell-by-cell DDA over [ta, tb]; ``cmax`` (per-cell max height) rejects most cells."""
    nx, ny = cmax.shape[1], cmax.shape[0]
    i, si, tnx, dtx = _dda_init(ox, dx, ta, x0, res, nx)
    j, sj, tny, dty = _dda_init(oy, dy, ta, y0, res, ny)
    fx0, fy0 = (ox - x0) / res, (oy - y0) / res
    du, dv = dx / res, dy / res
    c0 = fx0 - fy0
    inv_dd = 1.0 / (du - dv) if du != dv else INF
    t, zt = ta, oz + dz * ta
    while t < tb:
        if not (0 <= i < nx and 0 <= j < ny):
            return INF
        ux = tnx < tny
        te = min(tnx if ux else tny, tb)
        ze = oz + dz * te
        if min(zt, ze) <= cmax[j, i]:
            hit = _cell_hit(oz, dz, fx0, fy0, du, dv, c0, inv_dd, t, te, h, i, j)
            if hit < INF:
                return hit
        t, zt = te, ze
        # select, not branch: the x/y step order is unpredictable (measured ~20% faster)
        i = i + si if ux else i
        j = j if ux else j + sj
        tnx = tnx + dtx if ux else tnx
        tny = tny if ux else tny + dty
    return INF


@nb.njit(inline="always", **_JIT)
def march_terrain(ox, oy, oz, dx, dy, dz, tmin, tmax, h, cmax, x0, y0, res, tilemax, tile,
                  gmax) -> float:
    """Distance along the ray to the terrain mesh, INF if none within [tmin, tmax].

    ``tmin`` must be a distance before which the ray is known to be clear.
    Rays are clipped to the grid and to the highest terrain point ``gmax``. Short
    spans (up to ``SHORT_TILES`` tiles) march cells directly; longer ones march tiles first and
    descend into the tiles whose maximum the ray goes below.
    """
    nx, ny = cmax.shape[1], cmax.shape[0]
    ta, tb = tmin, tmax
    if dx == 0.0:
        if ox < x0 or ox > x0 + nx * res:
            return INF
    else:
        t1, t2 = (x0 - ox) / dx, (x0 + nx * res - ox) / dx
        ta, tb = max(ta, min(t1, t2)), min(tb, max(t1, t2))
    if dy == 0.0:
        if oy < y0 or oy > y0 + ny * res:
            return INF
    else:
        t1, t2 = (y0 - oy) / dy, (y0 + ny * res - oy) / dy
        ta, tb = max(ta, min(t1, t2)), min(tb, max(t1, t2))
    if dz >= 0.0:
        if oz + dz * ta > gmax:
            return INF
        if dz > 0.0:
            tb = min(tb, (gmax - oz) / dz)
    else:
        ta = max(ta, (oz - gmax) / -dz)
    if ta >= tb:
        return INF
    tsize = tile * res
    if tb - ta <= SHORT_TILES * tsize:
        return _march_cells(ox, oy, oz, dx, dy, dz, ta, tb, h, cmax, x0, y0, res)
    ntx, nty = tilemax.shape[1], tilemax.shape[0]
    i, si, tnx, dtx = _dda_init(ox, dx, ta, x0, tsize, ntx)
    j, sj, tny, dty = _dda_init(oy, dy, ta, y0, tsize, nty)
    t = ta
    while t < tb and 0 <= i < ntx and 0 <= j < nty:
        te = min(min(tnx, tny), tb)
        if min(oz + dz * t, oz + dz * te) <= tilemax[j, i]:
            hit = _march_cells(ox, oy, oz, dx, dy, dz, t, te, h, cmax, x0, y0, res)
            if hit < INF:
                return hit
        if tnx < tny:
            i += si
            t = tnx
            tnx += dtx
        else:
            j += sj
            t = tny
            tny += dty
    return INF


@nb.njit(**_JIT)
def cast_terrain(o, rot, dirs_s, idx, n, tstart, nch, dist, h, cmax, x0, y0, res, tilemax,
                 tile, gmax) -> None:
    """March rays ``idx[:n]``; dist[i] = min(dist[i], terrain distance).

    Ray i starts at ``tstart[i // nch]`` (clear before that, see ``raycull``).
    """
    for k in range(n):
        i = idx[k]
        x, y, z = dirs_s[i, 0], dirs_s[i, 1], dirs_s[i, 2]
        dx = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z
        dy = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z
        dz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z
        t = march_terrain(o[0], o[1], o[2], dx, dy, dz, max(tstart[i // nch], 0.0), dist[i],
                          h, cmax, x0, y0, res, tilemax, tile, gmax)
        if t < dist[i]:
            dist[i] = t


@nb.njit(**_JIT)
def ray_convex(ox, oy, oz, dx, dy, dz, planes, q0, q1) -> float:
    """First surface of the convex solid planes[q0:q1] along the ray (Cyrus-Beck)."""
    tn, tf = -INF, INF
    for q in range(q0, q1):
        den = planes[q, 0] * dx + planes[q, 1] * dy + planes[q, 2] * dz
        num = planes[q, 3] - (planes[q, 0] * ox + planes[q, 1] * oy + planes[q, 2] * oz)
        if den == 0.0:
            if num < 0.0:
                return INF
            continue
        t = num / den
        if den < 0.0:
            tn = max(tn, t)
        else:
            tf = min(tf, t)
        if tn > tf:
            return INF
    if tf < 0.0:
        return INF
    return tn if tn > 0.0 else tf


@nb.njit(**_JIT)
def cast_solids(o, rot, dirs_s, grid, tmax, planes, start, sphere, dist) -> None:
    """Splat convex solids onto the ray grid; dist[i] = min(dist[i], solid distance).

    ``grid`` = (ncol, nch, az0, daz, el0, del) of the sensor-frame ray grid.
    """
    ncol, nch = int(grid[0]), int(grid[1])
    az0, daz, el0, dele = grid[2], grid[3], grid[4], grid[5]
    for m in range(sphere.shape[0]):
        cx, cy, cz = sphere[m, 0] - o[0], sphere[m, 1] - o[1], sphere[m, 2] - o[2]
        rb = sphere[m, 3]
        dc = math.sqrt(cx * cx + cy * cy + cz * cz)
        if dc - rb > tmax:
            continue
        c_lo, c_hi, ch_lo, ch_hi = 0, ncol - 1, 0, nch - 1
        if dc > rb:
            sx = rot[0, 0] * cx + rot[1, 0] * cy + rot[2, 0] * cz  # rot^T c
            sy = rot[0, 1] * cx + rot[1, 1] * cy + rot[2, 1] * cz
            sz = rot[0, 2] * cx + rot[1, 2] * cy + rot[2, 2] * cz
            el = math.asin(min(max(sz / dc, -1.0), 1.0))
            rho = math.asin(rb / dc) + 1e-9
            ch_lo = max(int(math.ceil((el - rho - el0) / dele - 1e-9)), 0)
            ch_hi = min(int(math.floor((el + rho - el0) / dele + 1e-9)), nch - 1)
            if ch_lo > ch_hi:
                continue
            if abs(el) + rho < 0.5 * math.pi:
                w = math.asin(min(math.sin(rho) / math.cos(el), 1.0))
                az = math.atan2(sy, sx)
                c_lo = int(math.floor((az - w - az0) / daz))
                c_hi = int(math.ceil((az + w - az0) / daz))
                if c_hi - c_lo + 1 >= ncol:
                    c_lo, c_hi = 0, ncol - 1
        q0, q1 = start[m], start[m + 1]
        for c in range(c_lo, c_hi + 1):
            col = c % ncol
            for ch in range(ch_lo, ch_hi + 1):
                i = col * nch + ch
                x, y, z = dirs_s[i, 0], dirs_s[i, 1], dirs_s[i, 2]
                dx = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z
                dy = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z
                dz = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z
                t = ray_convex(o[0], o[1], o[2], dx, dy, dz, planes, q0, q1)
                if t < dist[i]:
                    dist[i] = t


@nb.njit(**_JIT)
def scatter(idx, n, values, cutoff, dist) -> None:
    """dist[idx[k]] = min(dist[idx[k]], values[k]) for k < n where values[k] < cutoff."""
    for k in range(n):
        if values[k] < cutoff and values[k] < dist[idx[k]]:
            dist[idx[k]] = values[k]


@nb.njit(**_JIT)
def gather_hits(dist, tmax, out_idx) -> int:
    """Indices with dist < tmax; returns count."""
    n = 0
    for i in range(dist.shape[0]):
        if dist[i] < tmax:
            out_idx[n] = i
            n += 1
    return n


@nb.njit(**_JIT)
def make_points(dist, idx, n, noise, sigma, rmin, rmax, dirs_s, nch, out, rings) -> int:
    """Noisy returns of rays idx[:n] as sensor-frame points; returns how many are kept.

    range = dist + sigma * noise[k]; kept when rmin <= range <= rmax. ``rings[m]``: the
    kept return's channel (ray ``i`` is channel ``i % nch``, 0 = the lowest beam).
    """
    m = 0
    for k in range(n):
        i = idx[k]
        r = dist[i] + sigma * noise[k]
        if rmin <= r <= rmax:
            out[m, 0] = dirs_s[i, 0] * r
            out[m, 1] = dirs_s[i, 1] * r
            out[m, 2] = dirs_s[i, 2] * r
            rings[m] = i % nch
            m += 1
    return m

