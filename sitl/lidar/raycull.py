"""Conservative ray culling before casting (both engines).

- ``candidates``: rays whose lowest point within ``tmax`` is not above a given height
  (the highest surface of the scene): rays that climb away from everything are
  skipped. Used for long ranges.
- ``horizon_candidates``: for short ranges (the sensing radius), a per-column horizon
  in the sensor frame built from the terrain tiles and solid bounding spheres near the
  sensor; only rays below their column's horizon can hit anything. When nothing is
  within range no ray is cast.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}
INF = np.inf


@nb.njit(**_JIT)
def candidates(o, rot, dirs_s, tmax, top, out_idx) -> int:
    """Indices of rays whose lowest point within tmax is not above ``top``; returns count."""
    n = 0
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    for i in range(dirs_s.shape[0]):
        dz = r20 * dirs_s[i, 0] + r21 * dirs_s[i, 1] + r22 * dirs_s[i, 2]
        if o[2] + tmax * min(dz, 0.0) <= top:
            out_idx[n] = i
            n += 1
    return n


@nb.njit(**_JIT)
def _mark_columns(hz, colmin, az_lo, az_hi, el_hi, dmin, az0, daz) -> None:
    """For the columns whose azimuth is in [az_lo, az_hi]: raise the horizon to el_hi and
    lower the nearest-geometry distance to dmin."""
    ncol = hz.shape[0]
    c_lo = int(math.floor((az_lo - az0) / daz))
    c_hi = int(math.ceil((az_hi - az0) / daz))
    if c_hi - c_lo + 1 >= ncol:
        c_lo, c_hi = 0, ncol - 1
    for c in range(c_lo, c_hi + 1):
        col = c % ncol
        if el_hi > hz[col]:
            hz[col] = el_hi
        if dmin < colmin[col]:
            colmin[col] = dmin


@nb.njit(**_JIT)
def horizon_candidates(o, rot, grid, tmax, tmax_h, tmin_h, x0, y0, tsize, sphere, hz,
                       colmin, out_idx) -> int:
    """Rays that may hit within tmax: those below the sensor-frame horizon of each column.

    The horizon of a column is the highest elevation (sensor frame) that any terrain
    tile (a box from its min to its max height) or solid bounding sphere within tmax
    reaches in that column's azimuth window. Conservative: a culled ray cannot hit.
    ``colmin[col]`` receives the distance of the nearest such tile or sphere: no ray of
    the column can hit anything closer, so marching may start there.
    """
    ncol, nch = int(grid[0]), int(grid[1])
    az0, daz, el0, dele = grid[2], grid[3], grid[4], grid[5]
    hz[:] = -INF
    colmin[:] = INF
    ox, oy, oz = o[0], o[1], o[2]
    nty, ntx = tmax_h.shape
    i0 = max(int(math.floor((ox - tmax - x0) / tsize)), 0)
    i1 = min(int(math.floor((ox + tmax - x0) / tsize)), ntx - 1)
    j0 = max(int(math.floor((oy - tmax - y0) / tsize)), 0)
    j1 = min(int(math.floor((oy + tmax - y0) / tsize)), nty - 1)
    everything = False
    # every ray's world elevation is >= the lowest channel's minus the sensor's tilt
    el_low = el0 - math.acos(min(max(rot[2, 2], -1.0), 1.0))
    tan_low = math.tan(el_low) if el_low > -0.5 * math.pi + 1e-6 else -INF
    for j in range(j0, j1 + 1):
        ya, yb = y0 + j * tsize, y0 + (j + 1) * tsize
        for i in range(i0, i1 + 1):
            xa, xb = x0 + i * tsize, x0 + (i + 1) * tsize
            za, zb = tmin_h[j, i], tmax_h[j, i]
            ex = max(max(xa - ox, ox - xb), 0.0)
            ey = max(max(ya - oy, oy - yb), 0.0)
            ez = max(max(za - oz, oz - zb), 0.0)
            dmin = math.sqrt(ex * ex + ey * ey + ez * ez)
            if dmin > tmax:
                continue
            if dmin == 0.0:
                everything = True
                break
            fx, fy = max(abs(xa - ox), abs(xb - ox)), max(abs(ya - oy), abs(yb - oy))
            if zb - oz < math.sqrt(fx * fx + fy * fy) * tan_low:
                continue  # the whole tile lies below the lowest ray
            qz_max, d_max, a_ref, lo, hi = -INF, 0.0, 0.0, 0.0, 0.0
            for k in range(8):
                cx = (xa if k & 1 == 0 else xb) - ox
                cy = (ya if k & 2 == 0 else yb) - oy
                cz = (za if k & 4 == 0 else zb) - oz
                qx = rot[0, 0] * cx + rot[1, 0] * cy + rot[2, 0] * cz
                qy = rot[0, 1] * cx + rot[1, 1] * cy + rot[2, 1] * cz
                qz = rot[0, 2] * cx + rot[1, 2] * cy + rot[2, 2] * cz
                qz_max = max(qz_max, qz)
                d_max = max(d_max, math.sqrt(cx * cx + cy * cy + cz * cz))
                a = math.atan2(qy, qx)
                if k == 0:
                    a_ref = a
                else:
                    da = (a - a_ref + math.pi) % (2 * math.pi) - math.pi
                    lo, hi = min(lo, da), max(hi, da)
            if qz_max > 0.0:
                el_hi = math.asin(min(qz_max / dmin, 1.0))
            else:
                el_hi = math.asin(qz_max / d_max)
            if el_hi < el0 - 1e-9:
                continue
            if hi - lo >= math.pi - 1e-6:
                lo, hi = -math.pi, math.pi
            _mark_columns(hz, colmin, a_ref + lo - 1e-9, a_ref + hi + 1e-9, el_hi, dmin, az0,
                          daz)
        if everything:
            break
    if not everything:
        for m in range(sphere.shape[0]):
            cx, cy, cz = sphere[m, 0] - ox, sphere[m, 1] - oy, sphere[m, 2] - oz
            rb = sphere[m, 3]
            dc = math.sqrt(cx * cx + cy * cy + cz * cz)
            if dc - rb > tmax:
                continue
            if dc <= rb:
                everything = True
                break
            qx = rot[0, 0] * cx + rot[1, 0] * cy + rot[2, 0] * cz
            qy = rot[0, 1] * cx + rot[1, 1] * cy + rot[2, 1] * cz
            qz = rot[0, 2] * cx + rot[1, 2] * cy + rot[2, 2] * cz
            el = math.asin(min(max(qz / dc, -1.0), 1.0))
            rho = math.asin(rb / dc) + 1e-9
            if abs(el) + rho < 0.5 * math.pi:
                w = math.asin(min(math.sin(rho) / math.cos(el), 1.0))
                az = math.atan2(qy, qx)
                _mark_columns(hz, colmin, az - w, az + w, el + rho, dc - rb, az0, daz)
            else:
                _mark_columns(hz, colmin, -math.pi, math.pi, el + rho, dc - rb, az0, daz)
    if everything:
        colmin[:] = 0.0
    n = 0
    for col in range(ncol):
        if everything:
            top = nch - 1
        else:
            top = min(int(math.floor((hz[col] - el0) / dele + 1e-9)), nch - 1) \
                if hz[col] > -INF else -1
        for ch in range(top + 1):
            out_idx[n] = col * nch + ch
            n += 1
    return n
