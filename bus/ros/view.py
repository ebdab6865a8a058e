"""What a log needs to open in 3D by ROS 2 conventions, derived from the messages the
recorder writes (issue 12): the TF tree, ``/clock``, the world, the goal, the flown path,
the moving aircraft and the icosahedron faces.

The recorder (:mod:`bus.log.record`) hands every message it writes to :meth:`RosView.derive`
on its writer thread and writes what comes back (CDR bytes on ROS 2 topics) just before
it, with the same log time. Everything derived depends on message contents only (sim
stamps, positions), never on the wall clock, so two runs of the same seeds give the same
derived payloads.

Topics (``<v>`` the vehicle; one vehicle per log, the first one seen, see
:class:`RosView`); latched ones are offered transient-local (:func:`latched`):

- ``/tf`` (tf2_msgs/msg/TFMessage): world -> base_link at each ``truth``;
- ``/tf_static`` (TFMessage, latched): base_link -> lidar, once per file, first;
- ``/clock`` (rosgraph_msgs/msg/Clock): the stack time of each step clock;
- ``/skyloop/<v>/viz/world`` (visualization_msgs/msg/MarkerArray, latched): terrain
  (a decimated TRIANGLE_LIST coloured by height), buildings, trunks, crowns, and the
  vehicle's body sphere; once per scenario and per file;
- ``/skyloop/<v>/viz/goal`` (MarkerArray, latched): at each START, the goal (a sphere
  of the goal radius), the start and a label;
- ``/skyloop/<v>/viz/aircraft`` (MarkerArray): the aircraft boxes at each ``truth``
  (scenarios with aircraft);
- ``/skyloop/<v>/viz/icosahedron`` (MarkerArray, frame-locked to ``lidar``): the
  occupied faces coloured by value, when the colours change; the edges once per
  radius and file;
- ``/skyloop/<v>/path`` (nav_msgs/msg/Path): the episode's true poses, on its 1st,
  ``path_every + 1``-th, ... pose and at END.

Frames: ``world`` (ENU, the root), ``base_link`` (body FLU, from ground truth: the scan
is taken at the true pose, so only the true pose puts the points where the world is;
the estimate has yaw only and noise), ``lidar`` (the VLP-16 at the body's origin, axes
the body's: an identity transform). Stamps are the messages' own (stack time, see
docs/interfaces.md "Logs in 3D"); static things (``/tf_static``, the world) are
stamped 0.

Geometry comes from a :class:`SceneSource` (the scenario's world, the icosahedron):
:mod:`bus.ros.scene` reads the simulator's and perception's own. A world (about 1 s:
the world, then the terrain's decimation) is built by ``worlds``: in the recorder a
process of its own (:class:`bus.ros.scene.WorldWorker`, so that the writer thread never
shares the interpreter lock with it), else a thread (:class:`ThreadWorlds`); its
markers are written with the first message after it is ready. The source's imports and
numba kernels warm up on a thread when the view is made, before any episode; nothing
on the writer thread waits for them. The per-step messages (``/tf``, the path, the
icosahedron) are written as CDR directly (:class:`_Cdr`, the same bytes as
``bus.messages.encode`` of the message objects, tested), not built as message objects
first: derived per step on the writer thread 0.05-0.08 ms instead of 0.14-0.16 (a
valley log replayed, issue 11 "Speed", 2026-12-03).
"""

from __future__ import annotations

import logging
import math
import struct
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from bus import keys
from bus import messages as m
from bus.task import TASK

log = logging.getLogger("skyloop.record")

FRAME_WORLD, FRAME_BASE, FRAME_LIDAR = "world", "base_link", "lidar"
TF, TF_STATIC, CLOCK = "/tf", "/tf_static", "/clock"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
CLOCK_MESSAGE = "rosgraph_msgs/msg/Clock"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"
PATH = "nav_msgs/msg/Path"
WORLD, GOAL, AIRCRAFT, ICOSAHEDRON = "world", "goal", "aircraft", "icosahedron"

_T = m.TYPESTORE.types
_Marker = _T["visualization_msgs/msg/Marker"]
_MarkerArray = _T[MARKER_ARRAY]
_ColorRGBA = _T["std_msgs/msg/ColorRGBA"]
_Duration = _T["builtin_interfaces/msg/Duration"]
_CompressedImage = _T["sensor_msgs/msg/CompressedImage"]
_MeshFile = _T["visualization_msgs/msg/MeshFile"]
_Transform = _T["geometry_msgs/msg/Transform"]
_TransformStamped = _T["geometry_msgs/msg/TransformStamped"]
_TFMessage = _T[TF_MESSAGE]
_Clock = _T[CLOCK_MESSAGE]
_Path = _T[PATH]
_EMPTY_U8 = np.zeros(0, dtype=np.uint8)

# colours (r, g, b, a)
TERRAIN_RAMP = ((0.30, 0.52, 0.24), (0.62, 0.55, 0.36), (0.86, 0.85, 0.80))
BUILDING = (0.62, 0.62, 0.68, 1.0)
TRUNK = (0.45, 0.30, 0.15, 1.0)
CROWN = (0.16, 0.45, 0.16, 1.0)
BODY = (0.95, 0.95, 0.95, 0.6)
AIRCRAFT_COLOUR = (1.0, 0.5, 0.0, 1.0)
GOAL_COLOUR = (0.1, 0.9, 0.2, 0.35)
START_COLOUR = (0.2, 0.4, 1.0, 0.8)
EDGE_COLOUR = (0.8, 0.8, 0.8, 0.5)
FACE_NEAR, FACE_FAR = (1.0, 0.0, 0.0), (1.0, 0.9, 0.0)  # value 1 ... value -> 0
FACE_ALPHA = 0.6


def viz_topic(vehicle: str, name: str) -> str:
    """``/skyloop/<vehicle>/viz/<name>`` (not a bus topic: only logs have it)."""
    return f"/{keys.PREFIX}/{keys.check_vehicle(vehicle)}/viz/{name}"


def path_topic(vehicle: str) -> str:
    """``/skyloop/<vehicle>/path``."""
    return f"/{keys.PREFIX}/{keys.check_vehicle(vehicle)}/path"


def latched(topic: str) -> bool:
    """Topics offered transient-local (latched), as a static TF broadcaster offers
    ``/tf_static``: a late subscriber of ``ros2 bag play`` still gets them."""
    return topic == TF_STATIC or topic.endswith(("/viz/" + WORLD, "/viz/" + GOAL))


# ----------------------------------------------------------------------------- geometry
@dataclass(frozen=True)
class Mesh:
    """Triangles: vertices (V, 3) float, triangles (T, 3) int."""

    vertices: np.ndarray
    triangles: np.ndarray

    @staticmethod
    def empty() -> Mesh:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64))

    @staticmethod
    def merge(parts: Sequence[tuple[np.ndarray, np.ndarray]]) -> Mesh:
        verts, tris, off = [], [], 0
        for v, t in parts:
            verts.append(np.asarray(v, np.float64).reshape(-1, 3))
            tris.append(np.asarray(t, np.int64).reshape(-1, 3) + off)
            off += len(verts[-1])
        return Mesh(np.concatenate(verts), np.concatenate(tris)) if verts else Mesh.empty()


@dataclass(frozen=True)
class WorldGeometry:
    """What the world markers show: terrain (decimated), buildings, trunks, crowns (each
    merged into one mesh) and the vehicle's body radius."""

    terrain: Mesh
    buildings: Mesh
    trunks: Mesh
    crowns: Mesh
    body_radius: float


class SceneSource(Protocol):
    """Where geometry comes from (:class:`bus.ros.scene.SitlScene`; tests pass fakes)."""

    def warm(self) -> None:
        """Load what the other calls need (called once, off the writer thread)."""

    def aircraft(self, scenario: str) -> Callable[[float], np.ndarray] | None:
        """``t -> (K, 8)`` boxes (cx, cy, cz, hx, hy, hz, cos yaw, sin yaw) of the
        scenario's aircraft at episode time ``t``; None without aircraft. Fast."""

    def world(self, scenario: str) -> WorldGeometry:
        """The scenario's static world (slow: run off the writer thread)."""

    def icosahedron(self) -> tuple[np.ndarray, list[list[int]]]:
        """The truncated icosahedron of circumradius 1: vertices (60, 3) and the 32
        faces (vertex indices, counterclockwise from outside), in observation order."""


def decimate_heightfield(heights: np.ndarray, x0: float, y0: float, res: float,
                         max_triangles: int = 4000, tolerance: float = 0.02
                         ) -> tuple[Mesh, float]:
    """A heightfield grid (``heights[iy, ix]`` at ``(x0 + ix res, y0 + iy res)``) as a
    triangle mesh of at most ``max_triangles``, and the largest vertical error left at
    the grid's vertices (m).

    Greedy insertion (Garland and Heckbert, "Fast polygonal approximation of terrains
    and height fields", 1995): a coarse regular grid of grid vertices (a quarter of the
    budget, corners and edges kept), then, round by round, the vertex farthest from the
    mesh inside each triangle, worst first (1/25 of the budget a round), re-triangulated
    (Delaunay), until every vertex is within ``tolerance`` or the budget is spent. The
    hills meet in creases (heights combine by maximum) that a regular grid cuts off
    (valley at 4,000 triangles: 1.1 m off at worst on a 1.25 m grid, 0.24 m this way).
    Triangles counterclockwise seen from above. About 1 s for a 221 x 221 grid.
    """
    import matplotlib.tri as mtri  # lazily: only a recorder writing a world needs it

    h = np.asarray(heights, dtype=np.float64)
    ny, nx = h.shape[0] - 1, h.shape[1] - 1
    max_vertices = max(4, max_triangles // 2)  # a triangulation has < 2 V triangles
    k = max(1, math.ceil(math.sqrt((nx + 1) * (ny + 1) / (max_vertices / 4))))
    ix = np.unique(np.append(np.arange(0, nx + 1, k), nx))
    iy = np.unique(np.append(np.arange(0, ny + 1, k), ny))
    chosen = np.zeros(h.shape, dtype=bool)
    chosen[np.ix_(iy, ix)] = True
    flat = chosen.reshape(-1)
    gx, gy = np.meshgrid(np.arange(nx + 1, dtype=np.float64), np.arange(ny + 1, dtype=np.float64))
    px, py, z = gx.reshape(-1), gy.reshape(-1), h.reshape(-1)
    batch = max(1, max_vertices // 25)
    while True:
        sel = np.flatnonzero(flat)
        tri = mtri.Triangulation(px[sel], py[sel])
        inside = np.asarray(tri.get_trifinder()(px, py))  # -1: outside (never: corners)
        plane = tri.calculate_plane_coefficients(z[sel])[inside]  # z = a x + b y + c
        err = np.abs(plane[:, 0] * px + plane[:, 1] * py + plane[:, 2] - z)
        err[inside < 0] = np.inf
        err[sel] = 0.0
        room = max_vertices - len(sel)
        worst = float(err.max())
        if worst <= tolerance or room <= 0:
            break
        order = np.lexsort((-err, inside))  # by triangle, worst first within each
        first = order[np.r_[True, inside[order][1:] != inside[order][:-1]]]
        cand = first[err[first] > tolerance]
        flat[cand[np.argsort(-err[cand])][:min(room, batch)]] = True
    tris = tri.triangles.astype(np.int64)
    verts = np.column_stack([x0 + px[sel] * res, y0 + py[sel] * res, z[sel]])
    a, b, c = verts[tris[:, 0], :2], verts[tris[:, 1], :2], verts[tris[:, 2], :2]
    cw = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]) < 0
    tris[cw] = tris[cw][:, [0, 2, 1]]
    return Mesh(verts, tris), worst


# ----------------------------------------------------------------------------- messages
def _rgba(c: Sequence[float], alpha: float | None = None) -> Any:
    r, g, b = (float(v) for v in c[:3])
    a = float(alpha if alpha is not None else (c[3] if len(c) > 3 else 1.0))
    return _ColorRGBA(r=r, g=g, b=b, a=a)


def _pose(position: Sequence[float] = (0.0, 0.0, 0.0),
          quaternion_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0)) -> Any:
    x, y, z = (float(v) for v in position)
    qx, qy, qz, qw = (float(v) for v in quaternion_xyzw)
    return m.Pose(position=m.Point(x=x, y=y, z=z),
                  orientation=m.Quaternion(x=qx, y=qy, z=qz, w=qw))


def marker(ns: str, kind: int, stamp_s: float, frame_id: str = FRAME_WORLD, *, id: int = 0,
           position: Sequence[float] = (0.0, 0.0, 0.0),
           quaternion_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
           scale: Sequence[float] = (1.0, 1.0, 1.0), color: Sequence[float] = (1, 1, 1, 1),
           points: np.ndarray | None = None, colors: np.ndarray | None = None,
           text: str = "", frame_locked: bool = False) -> Any:
    """A ``visualization_msgs/Marker`` (ADD, lifetime 0: until replaced). ``points``
    (N, 3) and ``colors`` (N, 4) for lists; ``colors`` per point overrides ``color``."""
    pts = [] if points is None else \
        [m.Point(x=x, y=y, z=z) for x, y, z in np.asarray(points, np.float64).tolist()]
    cols = [] if colors is None else \
        [_ColorRGBA(r=r, g=g, b=b, a=a) for r, g, b, a in np.asarray(colors, np.float64).tolist()]
    sx, sy, sz = (float(v) for v in scale)
    return _Marker(
        header=m.header(stamp_s, frame_id), ns=ns, id=int(id), type=int(kind),
        action=_Marker.ADD, pose=_pose(position, quaternion_xyzw),
        scale=m.Vector3(x=sx, y=sy, z=sz), color=_rgba(color),
        lifetime=_Duration(sec=0, nanosec=0), frame_locked=bool(frame_locked), points=pts,
        colors=cols, texture_resource="",
        texture=_CompressedImage(header=m.header(0.0), format="", data=_EMPTY_U8),
        uv_coordinates=[], text=text, mesh_resource="",
        mesh_file=_MeshFile(filename="", data=_EMPTY_U8), mesh_use_embedded_materials=False)


def mesh_marker(ns: str, mesh: Mesh, color: Sequence[float], stamp_s: float = 0.0,
                frame_id: str = FRAME_WORLD, vertex_colors: np.ndarray | None = None,
                frame_locked: bool = False) -> Any:
    """A TRIANGLE_LIST marker of ``mesh`` (three points a triangle); ``vertex_colors``
    (V, 4) colours the mesh's vertices."""
    tris = np.asarray(mesh.triangles, np.int64).reshape(-1)
    cols = None if vertex_colors is None else np.asarray(vertex_colors)[tris]
    return marker(ns, _Marker.TRIANGLE_LIST, stamp_s, frame_id, color=color,
                  points=np.asarray(mesh.vertices)[tris], colors=cols, frame_locked=frame_locked)


def marker_array(markers: Sequence[Any]) -> Any:
    return _MarkerArray(markers=list(markers))


def transform(parent: str, child: str, stamp_s: float, translation: Sequence[float],
              quaternion_xyzw: Sequence[float]) -> Any:
    """``geometry_msgs/TransformStamped``: ``child``'s pose in ``parent``."""
    x, y, z = (float(v) for v in translation)
    qx, qy, qz, qw = (float(v) for v in quaternion_xyzw)
    return _TransformStamped(header=m.header(stamp_s, parent), child_frame_id=child,
                             transform=_Transform(translation=m.Vector3(x=x, y=y, z=z),
                                                  rotation=m.Quaternion(x=qx, y=qy, z=qz,
                                                                        w=qw)))


def tf_message(transforms: Sequence[Any]) -> Any:
    return _TFMessage(transforms=list(transforms))


def clock(stamp: Any) -> Any:
    """``rosgraph_msgs/Clock`` at a ``builtin_interfaces/Time``."""
    return _Clock(clock=stamp)


def static_tf() -> Any:
    """``/tf_static``: base_link -> lidar, identity (the scan is in the body frame at the
    body's origin, see ``sitl.lidar.scanner``), stamped 0 (valid at all times)."""
    return tf_message([transform(FRAME_BASE, FRAME_LIDAR, 0.0, (0, 0, 0), (0, 0, 0, 1))])


def terrain_colours(z: np.ndarray) -> np.ndarray:
    """(V, 4) colours by height: green low, tan, light grey high."""
    z = np.asarray(z, np.float64)
    span = float(z.max() - z.min()) if len(z) else 0.0
    f = (z - z.min()) / span if span > 0 else np.zeros_like(z)
    ramp = np.array(TERRAIN_RAMP)
    pos = f * (len(ramp) - 1)
    i = np.minimum(pos.astype(np.int64), len(ramp) - 2)
    w = (pos - i)[:, None]
    rgb = ramp[i] * (1 - w) + ramp[i + 1] * w
    return np.column_stack([rgb, np.ones(len(z))])


def world_markers(geo: WorldGeometry) -> Any:
    """The static world: terrain coloured by height, buildings, trunks, crowns (frame
    world, stamp 0) and the vehicle's body sphere (frame base_link, frame-locked)."""
    out = [mesh_marker("terrain", geo.terrain, (1, 1, 1, 1),
                       vertex_colors=terrain_colours(geo.terrain.vertices[:, 2]))]
    for ns, mesh, colour in (("buildings", geo.buildings, BUILDING),
                             ("trunks", geo.trunks, TRUNK), ("crowns", geo.crowns, CROWN)):
        if len(mesh.triangles):
            out.append(mesh_marker(ns, mesh, colour))
    d = 2.0 * geo.body_radius
    out.append(marker("body", _Marker.SPHERE, 0.0, FRAME_BASE, scale=(d, d, d), color=BODY,
                      frame_locked=True))
    return marker_array(out)


def goal_markers(start: Sequence[float], goal: Sequence[float], stamp_s: float,
                 goal_radius: float, label: str) -> Any:
    """The episode's goal (a sphere of the goal radius), its start and a label."""
    d = 2.0 * goal_radius
    g = [float(v) for v in goal]
    return marker_array([
        marker(GOAL, _Marker.SPHERE, stamp_s, position=g, scale=(d, d, d), color=GOAL_COLOUR),
        marker("start", _Marker.SPHERE, stamp_s, position=start, scale=(0.4, 0.4, 0.4),
               color=START_COLOUR),
        marker("label", _Marker.TEXT_VIEW_FACING, stamp_s, position=(g[0], g[1], g[2] + d),
               scale=(0.0, 0.0, 0.6), color=(1, 1, 1, 1), text=label)])


def aircraft_markers(boxes: np.ndarray, stamp_s: float) -> Any:
    """One CUBE a box (cx, cy, cz, hx, hy, hz, cos yaw, sin yaw)."""
    out = []
    for k, (cx, cy, cz, hx, hy, hz, c, s) in enumerate(np.asarray(boxes, np.float64)):
        yaw = math.atan2(s, c)
        out.append(marker(AIRCRAFT, _Marker.CUBE, stamp_s, id=k, position=(cx, cy, cz),
                          quaternion_xyzw=(0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)),
                          scale=(2 * hx, 2 * hy, 2 * hz), color=AIRCRAFT_COLOUR))
    return marker_array(out)


def face_colours(values: np.ndarray) -> np.ndarray:
    """(32, 4) colours of face values, yellow (value near 0) to red (1 and above); a
    value of 0 (free: no return inside the solid on that face) fully transparent. In
    both encodings a larger value means a return nearer the vehicle: ``distance`` is
    the nearest return's distance from the face centre over the radius, ``proximity``
    1 - its distance from the vehicle over the radius."""
    v = np.asarray(values, np.float64)
    f = np.clip(v, 0.0, 1.0)[:, None]
    rgb = np.array(FACE_FAR) * (1 - f) + np.array(FACE_NEAR) * f
    out = np.column_stack([rgb, np.full(len(v), FACE_ALPHA)])
    out[~(v > 0.0), 3] = 0.0
    return out


def fan_triangles(faces: Sequence[Sequence[int]]) -> tuple[np.ndarray, np.ndarray]:
    """Convex faces (vertex indices, in order) as a triangle fan each: triangles (T, 3)
    and the face each one belongs to (T,)."""
    tris, owner = [], []
    for i, face in enumerate(faces):
        for k in range(1, len(face) - 1):
            tris.append((face[0], face[k], face[k + 1]))
            owner.append(i)
    return np.array(tris, np.int64).reshape(-1, 3), np.array(owner, np.int64)


def icosahedron_markers(vertices: np.ndarray, faces: Sequence[Sequence[int]],
                        values: np.ndarray, radius: float, stamp_s: float,
                        edges: bool = True) -> Any:
    """The truncated icosahedron of ``radius`` around the lidar frame, frame-locked (it
    follows the vehicle between messages): the occupied faces (value > 0,
    fan-triangulated) each in the colour of its value (:func:`face_colours`), or a
    DELETE of them when every face is free, and (``edges``) the solid's 90 edges."""
    verts = np.asarray(vertices, np.float64) * float(radius)
    cols = face_colours(values)
    tris, owner = fan_triangles(faces)
    hit = cols[owner, 3] > 0.0
    if hit.any():
        out = [marker(ICOSAHEDRON, _Marker.TRIANGLE_LIST, stamp_s, FRAME_LIDAR,
                      points=verts[tris[hit].reshape(-1)],
                      colors=np.repeat(cols[owner[hit]], 3, axis=0), frame_locked=True)]
    else:
        out = [marker(ICOSAHEDRON, _Marker.TRIANGLE_LIST, stamp_s, FRAME_LIDAR,
                      frame_locked=True)]
        out[0].action = _Marker.DELETE
    if edges:
        pairs = sorted({(min(a, b), max(a, b)) for face in faces
                        for a, b in zip(face, [*face[1:], face[0]], strict=True)})
        out.append(marker(ICOSAHEDRON + "_edges", _Marker.LINE_LIST, stamp_s, FRAME_LIDAR,
                          scale=(0.02, 0.0, 0.0), color=EDGE_COLOUR,
                          points=verts[np.array(pairs, np.int64).reshape(-1)],
                          frame_locked=True))
    return marker_array(out)


def icosahedron_cdr(vertices: np.ndarray, faces: Sequence[Sequence[int]],
                    values: np.ndarray, radius: float, stamp_s: float,
                    edges: bool = True) -> bytes:
    """``m.encode(icosahedron_markers(...))`` (the same bytes), written directly: the
    recorder derives one at most every step, and the message objects of its ~350
    points and colours cost ~0.1 ms a step to build and serialise."""
    verts = np.asarray(vertices, np.float64) * float(radius)
    cols = face_colours(values)
    (tris, owner), pairs = _solid(faces)
    hit = cols[owner, 3] > 0.0
    out = _Cdr()
    out.u32(2 if edges else 1)
    if hit.any():
        out.marker(ICOSAHEDRON, _Marker.TRIANGLE_LIST, _Marker.ADD, stamp_s, FRAME_LIDAR,
                   (1.0, 1.0, 1.0), (1.0, 1.0, 1.0, 1.0), verts[tris[hit].reshape(-1)],
                   np.repeat(cols[owner[hit]], 3, axis=0))
    else:
        out.marker(ICOSAHEDRON, _Marker.TRIANGLE_LIST, _Marker.DELETE, stamp_s,
                   FRAME_LIDAR, (1.0, 1.0, 1.0), (1.0, 1.0, 1.0, 1.0), None, None)
    if edges:
        out.marker(ICOSAHEDRON + "_edges", _Marker.LINE_LIST, _Marker.ADD, stamp_s,
                   FRAME_LIDAR, (0.02, 0.0, 0.0), EDGE_COLOUR,
                   verts[pairs.reshape(-1)], None)
    return bytes(out.buf)


_SOLID: list[Any] = [None, None, None]  # faces (the object), its fan, its edge pairs


def _solid(faces: Sequence[Sequence[int]]) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """:func:`fan_triangles` and the sorted edge pairs of ``faces``, kept for the last
    face list seen (the view's solid: one a run)."""
    if _SOLID[0] is not faces:
        pairs = sorted({(min(a, b), max(a, b)) for face in faces
                        for a, b in zip(face, [*face[1:], face[0]], strict=True)})
        _SOLID[:] = [faces, fan_triangles(faces), np.array(pairs, np.int64)]
    return _SOLID[1], _SOLID[2]


class _Cdr:
    """Little-endian CDR (the encapsulation rosbags writes), aligned as ROS 2 aligns:
    from the first byte after the 4-byte header."""

    def __init__(self, phase: int = 0) -> None:
        # ``phase`` bytes stand for what precedes (they align what follows as there)
        self.buf = bytearray(b"\x00\x01\x00\x00" + bytes(phase))
        self.phase, self.count = phase, 0

    def align(self, n: int) -> None:
        pad = -(len(self.buf) - 4) % n
        if pad:
            self.buf += bytes(pad)

    def u32(self, v: int) -> None:
        self.align(4)
        self.buf += _U32.pack(v)

    def string(self, text: str) -> None:
        data = text.encode() + b"\x00"
        self.u32(len(data))
        self.buf += data

    def time(self, stamp_s: float) -> None:
        t = m.time_msg(stamp_s)
        self.stamp(t.sec, t.nanosec)

    def stamp(self, sec: int, nanosec: int) -> None:
        self.align(4)
        self.buf += _TIME.pack(sec, nanosec)

    def doubles(self, values: Sequence[float]) -> None:
        self.align(8)
        self.buf += struct.pack(f"<{len(values)}d", *values)

    def marker(self, ns: str, kind: int, action: int, stamp_s: float, frame_id: str,
               scale: Sequence[float], color: Sequence[float], points: np.ndarray | None,
               colors: np.ndarray | None) -> None:
        """A frame-locked ``visualization_msgs/Marker`` at the identity pose, lifetime 0,
        nothing else set: what :func:`marker` makes of these arguments."""
        self.time(stamp_s)
        self.string(frame_id)
        self.string(ns)
        self.align(4)
        self.buf += _MARKER_IDS.pack(0, int(kind), int(action))
        self.align(8)
        self.buf += _POSE_SCALE.pack(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0,
                                     *(float(v) for v in scale))
        self.buf += _RGBA.pack(*(float(v) for v in color))  # 8-aligned: no padding
        self.buf += _TIME.pack(0, 0)
        self.buf += b"\x01"  # frame_locked
        n = 0 if points is None else len(points)
        self.u32(n)
        if n:
            self.align(8)
            self.buf += np.ascontiguousarray(points, "<f8").tobytes()
        k = 0 if colors is None else len(colors)
        self.u32(k)
        if k:
            self.buf += np.ascontiguousarray(colors, "<f4").tobytes()
        self.string("")  # texture_resource
        self.time(0.0)  # texture: header, format, data
        self.string("")
        self.string("")
        self.u32(0)
        self.u32(0)  # uv_coordinates
        self.string("")  # text
        self.string("")  # mesh_resource
        self.string("")  # mesh_file: filename, data
        self.u32(0)
        self.buf += b"\x00"  # mesh_use_embedded_materials


_U32 = struct.Struct("<I")
_TIME = struct.Struct("<iI")
_MARKER_IDS = struct.Struct("<3i")
_POSE_SCALE = struct.Struct("<10d")
_RGBA = struct.Struct("<4f")


# ----------------------------------------------------------------------------- the view
class WorldRequest:
    """A result to come: ``done`` is set once ``result`` (or ``error``) is there."""

    def __init__(self) -> None:
        self.result: Any = None
        self.error: BaseException | None = None
        self.done = threading.Event()

    def set(self, result: Any, error: BaseException | None = None) -> None:
        self.result, self.error = result, error
        self.done.set()


def _in_thread(fn: Callable[[], Any], name: str) -> WorldRequest:
    """Run ``fn`` on a daemon thread (a closing recorder never waits for it)."""
    req = WorldRequest()

    def run() -> None:
        try:
            req.set(fn())
        except BaseException as err:  # noqa: BLE001 - reported by the view
            req.set(None, err)

    threading.Thread(target=run, name=name, daemon=True).start()
    return req


class ThreadWorlds:
    """World markers built on a thread of the calling process (tests, small scenes; the
    recorder uses :class:`bus.ros.scene.WorldWorker`, a process of its own)."""

    def __init__(self, scene: SceneSource) -> None:
        self.scene = scene

    def request(self, scenario: str) -> WorldRequest:
        return _in_thread(lambda: m.encode(world_markers(self.scene.world(scenario))),
                          "skyloop-record-world")

    def close(self) -> None:
        pass


class RosView:
    """Derives the ROS 2 log topics (module docstring) from the messages written.

    ``derive(vehicle, topic, msg, file_index)`` takes each message the recorder writes
    (decoded; ``topic`` the skyloop name) and the index of the log file it goes to, and
    returns ``(ros topic, type, CDR bytes)`` to write before it. One vehicle: the first
    whose messages it sees; others' are counted (``other_vehicle``), frames being
    unprefixed. ``path_every``: the path goes out on the 1st, ``path_every + 1``-th, ...
    pose of an episode and at its END. Aircraft positions use the episode time (stamp -
    START stamp), the simulator's world clock of seeded episodes; in free flight
    (``--policy none``, ``--goals gcs``) that clock runs on from the ground phase, so the
    aircraft shown are not exact there. Counters (:attr:`counts`): ``derived``,
    ``other_vehicle``, ``scene_errors``.
    """

    def __init__(self, scene: SceneSource | None, *, path_every: int = 10,
                 goal_radius: float = TASK.goal_radius, worlds: Any = None) -> None:
        if path_every < 1:
            raise ValueError(f"path_every must be >= 1, got {path_every}")
        self.scene = scene
        self.worlds = worlds if worlds is not None or scene is None else ThreadWorlds(scene)
        self.path_every = path_every
        self.goal_radius = goal_radius
        self.counts = {"derived": 0, "other_vehicle": 0, "scene_errors": 0}
        self.vehicle: str | None = None
        self._file = -1  # the file /tf_static (and the world, goal) went to
        self._scenario: str | None = None
        self._build: WorldRequest | None = None
        self._fleet: WorldRequest | None = None
        self._world: bytes | None = None
        self._world_file = -1
        self._goal: bytes | None = None
        self._aircraft: Callable[[float], np.ndarray] | None = None
        self._episode_start_ns: int | None = None
        self._path: list[tuple[int, int, str, tuple[float, ...]]] = []  # stamp, frame, pose
        self._path_sent = 0
        self._path_cdr: _Cdr | None = None
        self._ico: tuple[np.ndarray, list[list[int]]] | None = None
        self._ico_key: tuple | None = None
        self._ico_failed = False
        self._warm: WorldRequest | None = None
        if scene is not None:
            self._warm = _in_thread(scene.warm, "skyloop-record-warm")

    def _scene_error(self, what: str, err: BaseException) -> None:
        self.counts["scene_errors"] += 1
        log.warning("log view: %s failed: %s", what, err)

    # ------------------------------------------------------------------ per message
    def derive(self, vehicle: str, topic: str, msg: Any, file_index: int
               ) -> list[tuple[str, str, bytes]]:
        if self.vehicle is None:
            self.vehicle = vehicle
        elif vehicle != self.vehicle:
            self.counts["other_vehicle"] += 1
            return []
        out: list[tuple[str, str, bytes]] = []
        if file_index != self._file:  # a new file: what is latched goes first
            self._file = file_index
            out.append((TF_STATIC, TF_MESSAGE, m.encode(static_tf())))
            if self._goal is not None:
                out.append((viz_topic(vehicle, GOAL), MARKER_ARRAY, self._goal))
        if topic == keys.EPISODE:
            out += self._episode(vehicle, msg)
        elif topic == keys.TRUTH:
            out += self._truth(vehicle, msg)
        elif topic == keys.CLOCK:
            out.append((CLOCK, CLOCK_MESSAGE, m.encode(clock(msg.sim_time))))
        elif topic == keys.OBSERVATION:
            out += self._observation(vehicle, msg)
        out += self._world_ready(vehicle)
        self.counts["derived"] += len(out)
        return out

    def _episode(self, vehicle: str, msg: Any) -> list[tuple[str, str, bytes]]:
        if msg.event == m.END:
            self._episode_start_ns = None
            return self._path_msg(vehicle)
        if msg.event != m.START:
            return []
        stamp_s = m.seconds(msg.header.stamp)
        self._episode_start_ns = m.nanoseconds(msg.header.stamp)
        self._path, self._path_sent, self._path_cdr = [], 0, None
        scenario = str(msg.scenario)
        if scenario and scenario != self._scenario and self.scene is not None:
            self._scenario, self._world, self._aircraft = scenario, None, None
            scene, warm, self._fleet = self.scene, self._warm, None
            if warm is None or warm.done.is_set():  # a TOML read and a few arrays: ms
                try:
                    self._aircraft = scene.aircraft(scenario)
                except Exception as err:  # noqa: BLE001 - counted; the rest is written
                    self._scene_error(f"aircraft of {scenario}", err)
            else:  # imports still running: never waited for on the writer thread

                def fleet() -> Any:
                    warm.done.wait()
                    return scene.aircraft(scenario)

                self._fleet = _in_thread(fleet, "skyloop-record-fleet")
            self._build = self.worlds.request(scenario)
        s, g = msg.start, msg.goal
        label = f"episode {msg.episode} (seed {msg.seed})"
        self._goal = m.encode(goal_markers((s.x, s.y, s.z), (g.x, g.y, g.z), stamp_s,
                                           self.goal_radius, label))
        return [(viz_topic(vehicle, GOAL), MARKER_ARRAY, self._goal)]

    def _truth(self, vehicle: str, msg: Any) -> list[tuple[str, str, bytes]]:
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        stamp_s = m.seconds(msg.header.stamp)
        t = m.time_msg(stamp_s)
        frame = msg.header.frame_id or FRAME_WORLD
        pose = (float(p.x), float(p.y), float(p.z), float(q.x), float(q.y), float(q.z),
                float(q.w))
        tf = _Cdr()  # m.encode(tf_message([transform(frame, child, stamp_s, ...)]))
        tf.u32(1)
        tf.stamp(t.sec, t.nanosec)
        tf.string(frame)
        tf.string(msg.child_frame_id or FRAME_BASE)
        tf.doubles(pose)
        out = [(TF, TF_MESSAGE, bytes(tf.buf))]
        if self._episode_start_ns is None:
            return out
        self._path.append((t.sec, t.nanosec, frame, pose))
        if len(self._path) % self.path_every == 1 or self.path_every == 1:
            out += self._path_msg(vehicle)
        f = self._fleet
        if f is not None and f.done.is_set():  # ready: the aircraft from now on
            self._fleet, self._aircraft = None, f.result
            if f.error is not None:
                self._scene_error(f"aircraft of {self._scenario}", f.error)
        if self._aircraft is not None:
            t = (m.nanoseconds(msg.header.stamp) - self._episode_start_ns) / 1e9
            out.append((viz_topic(vehicle, AIRCRAFT), MARKER_ARRAY,
                        m.encode(aircraft_markers(self._aircraft(t), stamp_s))))
        return out

    def _path_msg(self, vehicle: str) -> list[tuple[str, str, bytes]]:
        if not self._path or len(self._path) == self._path_sent:  # END right after one
            return []
        self._path_sent = n = len(self._path)
        sec, nanosec, frame, _ = self._path[-1]
        head = _Cdr()  # the header of the last pose, then the poses (PoseStamped)
        head.stamp(sec, nanosec)
        head.string(frame)
        head.u32(n)
        phase = (len(head.buf) - 4) % 8
        w = self._path_cdr  # the poses so far, written once, where they start mod 8
        if w is None or w.phase != phase:
            w = self._path_cdr = _Cdr(phase)
        for sec, nanosec, frame, pose in self._path[w.count:]:
            w.stamp(sec, nanosec)
            w.string(frame)
            w.doubles(pose)
        w.count = n
        return [(path_topic(vehicle), PATH, bytes(head.buf) + w.buf[4 + phase:])]

    def _observation(self, vehicle: str, msg: Any) -> list[tuple[str, str, bytes]]:
        if self.scene is None or self._ico_failed:
            return []
        if self._ico is None:
            if self._warm is not None and not self._warm.done.is_set():
                return []  # not before the imports are done (off this thread)
            try:
                self._ico = self.scene.icosahedron()
            except Exception as err:  # noqa: BLE001 - counted, not tried again
                self._scene_error("icosahedron", err)
                self._ico_failed = True
                return []
        values = m.observation_values(msg)[-1, :TASK.faces].astype(np.float64)
        radius = float(msg.radius) if msg.radius > 0 else TASK.ico_radius
        colours = np.round(np.clip(values, 0.0, 1.0) * 32).astype(int) * (values > 0)
        key = (radius, self._file, tuple(colours.tolist()))
        if key == self._ico_key:
            return []
        edges = self._ico_key is None or self._ico_key[:2] != key[:2]  # new radius or file
        self._ico_key = key
        data = icosahedron_cdr(*self._ico, values, radius, m.seconds(msg.header.stamp),
                               edges=edges)
        return [(viz_topic(vehicle, ICOSAHEDRON), MARKER_ARRAY, data)]

    def _world_ready(self, vehicle: str) -> list[tuple[str, str, bytes]]:
        b = self._build
        if b is not None and b.done.is_set():
            self._build = None
            if b.error is not None:
                self._scene_error(f"world of {self._scenario}", b.error)
            else:
                self._world, self._world_file = b.result, -1
        if self._world is None or self._world_file == self._file:
            return []
        self._world_file = self._file
        return [(viz_topic(vehicle, WORLD), MARKER_ARRAY, self._world)]

    def finish(self, file_index: int, wait_s: float) -> list[tuple[str, str, bytes]]:
        """At the end of a recording: wait up to ``wait_s`` for a world being built and
        return its markers if they are not in file ``file_index`` yet."""
        if self._build is not None:
            self._build.done.wait(wait_s)
        if self.vehicle is None or file_index != self._file:
            return []
        out = self._world_ready(self.vehicle)
        self.counts["derived"] += len(out)
        return out

    def close(self) -> None:
        """End the world builder (a worker process)."""
        if self.worlds is not None:
            self.worlds.close()

    def counts_snapshot(self) -> dict[str, int]:
        """``other_vehicle`` and ``scene_errors`` (the recorder counts what it wrote)."""
        return {k: v for k, v in self.counts.items() if k != "derived"}
