"""Truncated icosahedron ("soccer ball") geometry for point-cloud simplification.

Paper section 3.1: the UAV is wrapped in a virtual truncated icosahedron whose 32 faces
(12 pentagons, 20 hexagons) summarise the LiDAR point cloud (eq. 3.1 inclusion test,
eq. 3.2 per-face minimum, see :mod:`perception.faces`).

Construction
------------
1. Regular icosahedron: the 12 cyclic permutations of ``(0, +-1, +-phi)``,
   ``phi = (1 + sqrt 5) / 2`` (edge length 2, 30 edges, 20 triangles).
2. Truncation: cut every icosahedron edge ``(a, b)`` at one third from each end, i.e. take
   the points ``a + (b - a) / 3`` and ``a + 2 (b - a) / 3``. These are the 60 vertices;
   all 90 edges then have length 2/3 of the icosahedron's edge.
3. Scale so that the circumradius (distance of every vertex from the centre) equals
   ``radius`` **[choice]**: p_radius = 4 m is the circumradius, see abr-method.md.
4. Faces, as oriented planes ``n_i . p = d_i`` with outward unit normals ``n_i``:

   - pentagons (faces 0..11): ``n_i`` = direction of icosahedron vertex ``i`` (each
     icosahedron vertex is cut off by a pentagon);
   - hexagons (faces 12..31): ``n_i`` = direction of an icosahedron triangle centroid,
     which are exactly the 20 vertices of the dual dodecahedron
     (``(+-1, +-1, +-1)`` and the cyclic permutations of ``(0, +-phi, +-1/phi)``).

   ``d_i = max_v n_i . v`` over the vertices; the face is the set of vertices on that
   plane (5 or 6), ordered counterclockwise seen from outside (right-handed about
   ``n_i``). Face centre ``c_i = d_i n_i``. At radius 4: pentagon planes at 3.7569 m,
   hexagon planes at 3.6598 m, edge 1.6142 m (3.757 and 3.660 to three places).

Orientation (body frame FLU): the standard one above. The x, y and z axes pass through
the midpoints of hexagon-hexagon edges, so the solid is mirror-symmetric left/right,
front/back and up/down; straight ahead lies on the edge between faces "forward-left" and
"forward-right". The face order is fixed (it is part of the observation layout).
"""

from __future__ import annotations

import itertools

import numpy as np

PHI = (1.0 + np.sqrt(5.0)) / 2.0
N_FACES = 32
N_PENTAGONS = 12
N_HEXAGONS = 20


def icosahedron_vertices() -> np.ndarray:
    """The 12 vertices of the regular icosahedron, cyclic permutations of (0, +-1, +-phi)."""
    out = []
    for s1, s2 in itertools.product((1.0, -1.0), repeat=2):
        base = (0.0, s1 * 1.0, s2 * PHI)
        for k in range(3):  # cyclic permutations
            out.append(base[-k:] + base[:-k] if k else base)
    verts = np.array(out, dtype=np.float64)
    # Stable, readable order: sort lexicographically (z, then y, then x), top first.
    order = np.lexsort((-verts[:, 0], -verts[:, 1], -verts[:, 2]))
    return verts[order]


def _icosahedron_topology(verts: np.ndarray) -> tuple[list[tuple[int, int]], list[tuple]]:
    """Edges (pairs at distance 2) and triangles (mutually adjacent triples)."""
    n = len(verts)
    dist = np.linalg.norm(verts[:, None, :] - verts[None, :, :], axis=-1)
    adj = np.isclose(dist, 2.0)
    edges = [(i, j) for i in range(n) for j in range(i + 1, n) if adj[i, j]]
    tris = [
        (i, j, k)
        for i, j, k in itertools.combinations(range(n), 3)
        if adj[i, j] and adj[j, k] and adj[i, k]
    ]
    return edges, tris


def _order_ccw(points: np.ndarray, idx: np.ndarray, normal: np.ndarray) -> list[int]:
    """Order vertex indices counterclockwise around ``normal`` (seen from outside)."""
    centre = points[idx].mean(axis=0)
    u = points[idx[0]] - centre
    u /= np.linalg.norm(u)
    w = np.cross(normal, u)
    rel = points[idx] - centre
    ang = np.arctan2(rel @ w, rel @ u)
    return [int(i) for i in idx[np.argsort(ang)]]


class TruncatedIcosahedron:
    """Truncated icosahedron of circumradius ``radius`` centred on the UAV.

    Attributes (read-only arrays, float64):
        radius: circumradius p_radius (m); every vertex lies at this distance.
        vertices: (60, 3) vertex coordinates.
        edges: (90, 2) vertex index pairs.
        faces: 32 lists of vertex indices, each ordered counterclockwise seen from outside.
        normals: (32, 3) outward unit normals n_i (pentagons first).
        offsets: (32,) plane offsets d_i (n_i . p = d_i on face i).
        centres: (32, 3) face centres c_i = d_i n_i.
        normals_t, centres_t: (3, 32) C-contiguous transposes of the two above.
        is_pentagon: (32,) bool, True for faces 0..11.
        edge_length: the common edge length.
        inradius: min(d_i), the radius of the largest ball inside the solid.
    """

    def __init__(self, radius: float = 4.0) -> None:
        radius = float(radius)
        if not np.isfinite(radius) or radius <= 0.0:
            raise ValueError(f"radius must be a positive finite number, got {radius!r}")
        self.radius = radius

        ico = icosahedron_vertices()
        ico_edges, ico_tris = _icosahedron_topology(ico)
        # Step 2: two vertices per icosahedron edge, at 1/3 and 2/3.
        raw = []
        for a, b in ico_edges:
            raw.append(ico[a] + (ico[b] - ico[a]) / 3.0)
            raw.append(ico[a] + 2.0 * (ico[b] - ico[a]) / 3.0)
        raw_arr = np.array(raw)
        scale = radius / np.linalg.norm(raw_arr[0])
        vertices = raw_arr * scale

        # Step 4: face normals from icosahedron vertices and triangle centroids.
        tri_dirs = np.array([ico[list(t)].mean(axis=0) for t in ico_tris])
        tri_dirs = tri_dirs[np.lexsort((-tri_dirs[:, 0], -tri_dirs[:, 1], -tri_dirs[:, 2]))]
        dirs = np.vstack([ico, tri_dirs])
        normals = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        proj = vertices @ normals.T  # (60, 32)
        offsets = proj.max(axis=0)
        tol = 1e-9 * radius
        faces = []
        for i in range(N_FACES):
            on_plane = np.flatnonzero(proj[:, i] >= offsets[i] - tol)
            faces.append(_order_ccw(vertices, on_plane, normals[i]))

        # Edges: consecutive vertices around faces (each edge is shared by two faces).
        edge_set = set()
        for f in faces:
            for k in range(len(f)):
                a, b = f[k], f[(k + 1) % len(f)]
                edge_set.add((min(a, b), max(a, b)))
        edges = np.array(sorted(edge_set), dtype=np.int64)

        self.vertices = _frozen(vertices)
        self.edges = _frozen(edges)
        self.faces: list[list[int]] = faces
        self.normals = _frozen(normals)
        self.offsets = _frozen(offsets)
        self.centres = _frozen(offsets[:, None] * normals)
        # (3, 32) transposes: one contiguous row per coordinate, for vectorized kernels.
        self.normals_t = _frozen(normals.T)
        self.centres_t = _frozen(self.centres.T)
        self.is_pentagon = _frozen(np.arange(N_FACES) < N_PENTAGONS)
        self.edge_length = float(
            np.linalg.norm(vertices[edges[0, 0]] - vertices[edges[0, 1]])
        )
        self.inradius = float(offsets.min())

    @property
    def n_faces(self) -> int:
        """Number of faces (32)."""
        return N_FACES

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Eq. 3.1 inclusion test for (N, 3) points: True where n_i . p <= d_i for all i.

        A straightforward reference; :func:`perception.faces.face_values` has the fast path.
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return np.all(pts @ self.normals.T <= self.offsets, axis=1)

    def __repr__(self) -> str:
        return f"TruncatedIcosahedron(radius={self.radius})"


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a
