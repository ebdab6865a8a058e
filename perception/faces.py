"""Reduce a point cloud to the 32 truncated-icosahedron face values (paper section 3.1).

Points are UAV-centred (sensor frame, metres), as :meth:`sitl.lidar.scanner.Lidar.scan` returns
them. For each point ``p``:

- eq. 3.1, inclusion test: ``p`` is inside the solid when ``n_i . p <= d_i`` for all 32
  faces; points outside are ignored. Points on a face plane count as inside.
- eq. 3.2, assignment and reduction: an inside point belongs to the face whose centre
  ``c_i`` is nearest (ties: lowest face index); ``f_i = min |p - c_i|`` over the points
  of face ``i``, and ``f_i = 0`` when no point belongs to face ``i``. Nearest-centre
  assignment is the paper's rule; it differs from "the face cone the point lies in" for
  about 6 % of points spread uniformly in the solid. As in the paper, a point exactly at
  a face centre also gives ``f_i = 0`` (indistinguishable from "free"); with LiDAR noise
  this has measure zero.
- ``encoding="proximity"`` (beyond the paper, off by default): same inclusion and
  assignment, but ``f_i = 1 - min |p| / p_radius`` over the points of face ``i``
  (0 = free, 1 = touching the UAV), a value that grows monotonically as an obstacle
  approaches, unlike eq. 3.2's distance to the face centre.

Non-finite points (NaN, inf, as a LiDAR may report for no-return rays) are ignored and
counted as invalid (:func:`reduce_points` reports the count; so is a point so far away
that its squared norm overflows).

Speed: most points of a scan lie beyond the sphere of radius p_radius that circumscribes
the solid, so every point is first tested with ``|p|^2 <= p_radius^2`` (a superset test:
the solid lies inside its circumsphere); points within the inscribed sphere
``|p| <= min d_i`` are inside without the 32-plane test. The default backend is a single
numba loop over the points (no temporaries); a vectorized numpy backend gives the same
result and serves as fallback and cross-check. Measured (benchmarks/bench_perception.py,
medians, one core of the shared 2-core machine, so +-30 %): numba 0.06-0.09 ms for a
28,800-point VLP-16 scan with 5 % of the points inside, 0.8 ms when all 28,800 are inside
(worst case), 0.7-0.9 ms for 300,000 points; the numpy backend 0.5 ms, 6 ms and 6 ms
(with single-threaded OpenBLAS; its small matmuls become several times slower when
OpenBLAS threads compete for the two cores).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from perception.icosahedron import N_FACES, TruncatedIcosahedron

try:  # numba is a declared dependency; the numpy backend keeps this module importable.
    import numba

    _HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised only without numba
    numba = None
    _HAVE_NUMBA = False

ENCODINGS = ("distance", "proximity")
BACKENDS = ("auto", "numba", "numpy")
# The circumsphere pre-filter is a superset test; the slack keeps it one even when
# |p|^2 is rounded (float32 input, points at a vertex). The 32-plane test decides.
_PREFILTER_SLACK = 1e-6
_INSPHERE_SLACK = 1e-9


class FaceReduction(NamedTuple):
    """Result of :func:`reduce_points`."""

    values: np.ndarray  # (32,) float32 face values f_1..f_32
    n_inside: int  # points that passed the eq. 3.1 inclusion test
    n_invalid: int  # non-finite points (ignored)


def face_values(
    points: np.ndarray, ico: TruncatedIcosahedron, encoding: str = "distance"
) -> np.ndarray:
    """(32,) float32 face values of an (N, 3) point cloud: eq. 3.1 then eq. 3.2.

    Args:
        points: (N, 3) UAV-centred points, float32 or float64 (others are converted).
            N may be 0. NaN/inf rows are ignored.
        ico: the solid (its radius is p_radius).
        encoding: "distance" (eq. 3.2, f_i = min |p - c_i|, metres) or "proximity"
            (f_i = 1 - min |p| / p_radius, in [0, 1]).
    """
    return reduce_points(points, ico, encoding).values


def reduce_points(
    points: np.ndarray,
    ico: TruncatedIcosahedron,
    encoding: str = "distance",
    backend: str = "auto",
) -> FaceReduction:
    """Face values plus counts of inside and non-finite points (see :func:`face_values`).

    ``backend``: "auto" (numba when importable), "numba" or "numpy"; all give the same
    values up to floating-point ties.
    """
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding must be one of {ENCODINGS}, got {encoding!r}")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    pts = _as_points(points)
    proximity = encoding == "proximity"
    if pts.shape[0] == 0:
        return FaceReduction(np.zeros(N_FACES, dtype=np.float32), 0, 0)
    use_numba = backend == "numba" or (backend == "auto" and _HAVE_NUMBA)
    if use_numba:
        if not _HAVE_NUMBA:
            raise RuntimeError("backend='numba' requested but numba is not installed")
        best = np.full(N_FACES, np.inf)
        r2_max, r2_in = _thresholds(ico)
        n_in, n_bad = _reduce_numba(
            pts, ico.normals_t, ico.offsets, ico.centres_t, r2_max, r2_in, proximity, best
        )
    else:
        best, n_in, n_bad = _reduce_numpy(pts, ico, proximity)
    return FaceReduction(_finish(best, ico.radius, proximity), int(n_in), int(n_bad))


def _as_points(points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points)
    if pts.dtype != np.float32 and pts.dtype != np.float64:
        pts = pts.astype(np.float64)
    if pts.size == 0:
        return np.empty((0, 3), dtype=pts.dtype)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    return np.ascontiguousarray(pts)


def _thresholds(ico: TruncatedIcosahedron) -> tuple[float, float]:
    r2_max = ico.radius * ico.radius * (1.0 + _PREFILTER_SLACK)
    r2_in = ico.inradius * ico.inradius * (1.0 - _INSPHERE_SLACK)
    return r2_max, r2_in


def _finish(best: np.ndarray, radius: float, proximity: bool) -> np.ndarray:
    """Squared minima -> face values; faces without points -> 0."""
    hit = np.isfinite(best)
    out = np.zeros(N_FACES, dtype=np.float32)
    dist = np.sqrt(best[hit])
    out[hit] = (1.0 - dist / radius) if proximity else dist
    return out


def _reduce_numpy(
    pts: np.ndarray, ico: TruncatedIcosahedron, proximity: bool
) -> tuple[np.ndarray, int, int]:
    """Vectorized eq. 3.1 / 3.2 (no loop over points); returns squared minima."""
    r2_max, _ = _thresholds(ico)
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    r2 = x * x + y * y + z * z  # input precision: a pre-filter only (see _PREFILTER_SLACK)
    n_bad = int(np.count_nonzero(~(r2 < np.inf)))  # NaN or inf
    q = pts[r2 <= r2_max].astype(np.float64)  # NaN compares False: dropped here
    q = q[np.all(q @ ico.normals_t <= ico.offsets, axis=1)]  # eq. 3.1
    best = np.full(N_FACES, np.inf)
    if len(q):
        # eq. 3.2 assignment: argmin |p - c_i|^2 = argmin (|c_i|^2 - 2 p . c_i)
        key = np.einsum("ij,ij->i", ico.centres, ico.centres) - 2.0 * (q @ ico.centres_t)
        face = np.argmin(key, axis=1)
        if proximity:
            val = np.einsum("ij,ij->i", q, q)
        else:
            diff = q - ico.centres[face]
            val = np.einsum("ij,ij->i", diff, diff)
        np.minimum.at(best, face, val)
    return best, len(q), n_bad


if _HAVE_NUMBA:

    @numba.njit(cache=True, nogil=True)
    def _reduce_numba(pts, normals_t, offsets, centres_t, r2_max, r2_in, proximity, best):
        """One pass over the points: eq. 3.1 test, eq. 3.2 assignment, per-face minimum
        of the squared value into ``best`` (in place). Returns (n_inside, n_invalid).

        The nearest centre is found branch-free: each squared distance (>= 0, so its
        IEEE bits order like the value) gets the face index packed into its 6 lowest
        mantissa bits and the minimum of those integers is taken. Distances equal to
        within 2^-46 relative count as a tie, won by the lowest face index.
        """
        n_faces = offsets.shape[0]
        nx = normals_t[0]
        ny = normals_t[1]
        nz = normals_t[2]
        cx = centres_t[0]
        cy = centres_t[1]
        cz = centres_t[2]
        d2 = np.empty(n_faces)
        d2_bits = d2.view(np.int64)
        low = np.int64(63)
        n_in = 0
        n_bad = 0
        for k in range(pts.shape[0]):
            x = np.float64(pts[k, 0])
            y = np.float64(pts[k, 1])
            z = np.float64(pts[k, 2])
            r2 = x * x + y * y + z * z
            if not (r2 <= r2_max):  # outside the circumsphere, or NaN
                if not (r2 < np.inf):
                    n_bad += 1
                continue
            if r2 > r2_in:  # between in- and circumsphere: the eq. 3.1 plane test
                viol = -np.inf
                for i in range(n_faces):
                    viol = max(viol, nx[i] * x + ny[i] * y + nz[i] * z - offsets[i])
                if viol > 0.0:
                    continue
            n_in += 1
            for i in range(n_faces):  # eq. 3.2: squared distances to the face centres
                dx = x - cx[i]
                dy = y - cy[i]
                dz = z - cz[i]
                d2[i] = dx * dx + dy * dy + dz * dz
            packed = np.int64(0x7FFFFFFFFFFFFFFF)
            for i in range(n_faces):
                packed = min(packed, (d2_bits[i] & ~low) | i)
            face = packed & low
            val = r2 if proximity else d2[face]
            if val < best[face]:
                best[face] = val
        return n_in, n_bad

else:  # pragma: no cover
    _reduce_numba = None
