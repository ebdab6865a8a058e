"""Scene pictures (matplotlib's Agg canvas, no pyplot state): a top view and a 3D view of a world.

Top view: terrain heights (image) with the flight-level contour, obstacle footprints,
aircraft (boxes at time ``t`` and their loops), start, goal, paths, the UAV and its
LiDAR returns. 3D view: the terrain surface, obstacles, the LiDAR returns in world
coordinates and the 32 icosahedron faces around the UAV coloured by their values
(markers at ``ico_radius`` along each face normal, or the face polygons themselves
when ``face_polygons`` is given). With a UAV ``position`` the 3D view zooms to
``view_radius`` around it; otherwise it shows the navigable area.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib
import matplotlib.image as mpimg
import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from sitl.world.world import World

Vec = np.ndarray | None

MAX_POINTS_3D = 4000  # LiDAR returns drawn in 3D (subsampled evenly beyond this)
SOLID_COLOURS = {"building": "#8c8c8c", "trunk": "#6b4423", "crown": "#2e7d32"}


def render_scene(world: World, *, start: np.ndarray | None = None,
                 goal: np.ndarray | None = None, position: np.ndarray | None = None,
                 rotation: np.ndarray | None = None, points: np.ndarray | None = None,
                 face_values: np.ndarray | None = None, face_normals: np.ndarray | None = None,
                 paths: list[np.ndarray] | None = None, title: str = "",
                 out: str | Path | None = None, size: tuple[int, int] = (1200, 600),
                 t: float = 0.0, face_polygons: list[np.ndarray] | None = None,
                 ico_radius: float = 4.0, view_radius: float = 9.0) -> np.ndarray:
    """Draw the scene; returns RGB uint8 (H, W, 3) and writes a PNG to ``out`` if given.

    ``points``, ``face_normals`` and ``face_polygons`` (a list of (k,3) vertex arrays)
    are in the sensor/body frame of the UAV at ``position``; ``rotation`` maps them to
    the world (identity if omitted). ``t`` is the time at which aircraft are drawn.
    """
    width, height = size
    dpi = 100
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    rot = np.eye(3) if rotation is None else np.asarray(rotation, float)
    pos = None if position is None else np.asarray(position, float)
    world_pts = None
    if points is not None and len(points) and pos is not None:
        world_pts = np.asarray(points, float) @ rot.T + pos

    ax = fig.add_axes((0.06, 0.08, 0.40, 0.82))
    _top_view(ax, world, start, goal, pos, rot, world_pts, paths, t)
    ax3 = fig.add_axes((0.5, 0.02, 0.48, 0.92), projection="3d")
    _view_3d(ax3, world, start, goal, pos, rot, world_pts, paths, t, face_values,
             face_normals, face_polygons, ico_radius, view_radius)
    if title:
        fig.text(0.01, 0.985, title, fontsize=11, va="top", ha="left")
    canvas.draw()
    rgb = np.asarray(canvas.buffer_rgba())[..., :3].copy()
    if out is not None:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        mpimg.imsave(str(out), rgb)
    return rgb


def _top_view(ax: Axes, world: World, start: Vec, goal: Vec, pos: Vec, rot: np.ndarray,
              world_pts: Vec, paths: list[np.ndarray] | None, t: float) -> None:
    terrain = world.terrain
    xmin, xmax, ymin, ymax = world.bounds
    pad = 2.0
    im = ax.imshow(terrain.heights, origin="lower", extent=terrain.extent, cmap="terrain",
                   vmin=min(-1.0, float(terrain.heights.min())),
                   vmax=max(world.flight_level * 2.5, float(terrain.heights.max())))
    ax.figure.colorbar(im, ax=ax, fraction=0.04, pad=0.01, label="terrain height (m)")
    xs = terrain.x0 + np.arange(terrain.nx + 1) * terrain.res
    ys = terrain.y0 + np.arange(terrain.ny + 1) * terrain.res
    if terrain.heights.max() > world.flight_level:
        ax.contour(xs, ys, terrain.heights, levels=[world.flight_level], colors="crimson",
                   linewidths=0.8, linestyles="--")
    ax.plot([xmin, xmax, xmax, xmin, xmin], [ymin, ymin, ymax, ymax, ymin], "k-", lw=0.8)
    for s in world.solids:
        if s.kind == "trunk":
            continue
        hull = _hull_2d(s.vertices[:, :2])
        ax.fill(hull[:, 0], hull[:, 1], color=SOLID_COLOURS.get(s.kind, "grey"), alpha=0.85,
                lw=0.3, ec="k")
    for k, box in enumerate(world.aircraft_boxes(t)):
        loop = world.fleet.waypoints[k, : world.fleet.count[k]]
        ax.plot(loop[:, 0], loop[:, 1], ":", color="navy", lw=0.8)
        corners = _box_corners(box)[:4]
        ax.fill(corners[[0, 1, 3, 2], 0], corners[[0, 1, 3, 2], 1], color="navy", alpha=0.9)
    if world_pts is not None:
        ax.scatter(world_pts[:, 0], world_pts[:, 1], s=0.3, c="orange", alpha=0.6, lw=0)
    for i, path in enumerate(paths or []):
        path = np.asarray(path)
        if len(path):
            ax.plot(path[:, 0], path[:, 1], "-", lw=1.0, color=f"C{i % 10}", alpha=0.9)
    _markers(ax, start, goal, pos, rot, three_d=False)
    ax.set_xlim(xmin - pad, xmax + pad)
    ax.set_ylim(ymin - pad, ymax + pad)
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.set_aspect("equal")
    ax.set_title(f"top view ({world.scenario.name})", fontsize=10)


def _view_3d(ax: Axes, world: World, start: Vec, goal: Vec, pos: Vec, rot: np.ndarray,
             world_pts: Vec, paths: list[np.ndarray] | None, t: float, face_values: Vec,
             face_normals: Vec, face_polygons: list[np.ndarray] | None, ico_radius: float,
             view_radius: float) -> None:
    if pos is not None:
        x0, x1 = pos[0] - view_radius, pos[0] + view_radius
        y0, y1 = pos[1] - view_radius, pos[1] + view_radius
    else:
        x0, x1, y0, y1 = world.bounds
    ax.computed_zorder = False  # draw in order: returns and faces stay visible
    step = max((x1 - x0) / 40.0, world.terrain.res)
    gx, gy = np.meshgrid(np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step))
    gz = world.terrain_height(gx, gy)
    ax.plot_surface(gx, gy, gz, cmap="terrain", vmin=-1.0, vmax=world.flight_level * 2.5,
                    linewidth=0, antialiased=False, alpha=0.55, rstride=1, cstride=1,
                    shade=False, zorder=1)
    top = max(world.flight_level * 2.5, (pos[2] + ico_radius) if pos is not None else 0.0)
    tris, colours = [], []
    for s in world.solids:
        lo, hi = s.vertices.min(0), s.vertices.max(0)
        if hi[0] < x0 or lo[0] > x1 or hi[1] < y0 or lo[1] > y1:
            continue
        v = s.vertices.copy()
        v[:, 2] = np.minimum(v[:, 2], top)  # cut tall solids at the top of the view
        tris.extend(v[s.triangles])
        colours.extend([SOLID_COLOURS.get(s.kind, "grey")] * len(s.triangles))
    faces = [[0, 1, 3, 2], [4, 5, 7, 6], [0, 1, 5, 4], [2, 3, 7, 6], [0, 2, 6, 4], [1, 3, 7, 5]]
    for box in world.aircraft_boxes(t):
        if not (x0 <= box[0] <= x1 and y0 <= box[1] <= y1):
            continue
        c = _box_corners(box)
        tris.extend(c[f] for f in faces)
        colours.extend(["navy"] * 6)
    if tris:
        ax.add_collection3d(Poly3DCollection(tris, facecolors=colours, edgecolors="none",
                                             alpha=0.8, zorder=2))
    if world_pts is not None:
        sel = world_pts
        if len(sel) > MAX_POINTS_3D:
            sel = sel[:: int(np.ceil(len(sel) / MAX_POINTS_3D))]
        inside = ((sel[:, 0] >= x0) & (sel[:, 0] <= x1) & (sel[:, 1] >= y0) & (sel[:, 1] <= y1))
        sel = sel[inside]
        ax.scatter(sel[:, 0], sel[:, 1], sel[:, 2], s=1.5, c=sel[:, 2], cmap="autumn",
                   depthshade=False, zorder=3)
    if pos is not None and face_values is not None:
        _faces(ax, pos, rot, np.asarray(face_values, float), face_normals, face_polygons,
               ico_radius)
    for i, path in enumerate(paths or []):
        path = np.asarray(path)
        if len(path):
            ax.plot(path[:, 0], path[:, 1], path[:, 2], "-", lw=1.0, color=f"C{i % 10}")
    _markers(ax, start, goal, pos, rot, three_d=True)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_zlim(min(0.0, float(np.min(gz))), top)
    ax.set_box_aspect((x1 - x0, y1 - y0, max(top - min(0.0, float(np.min(gz))), 1.0)))
    ax.view_init(elev=28, azim=-60)
    ax.set_xlabel("x (m)", fontsize=8)
    ax.set_ylabel("y (m)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_title("3D: terrain, obstacles, LiDAR returns, icosahedron faces", fontsize=10)


def _faces(ax: Axes, pos: np.ndarray, rot: np.ndarray, values: np.ndarray, normals: Vec,
           polygons: list[np.ndarray] | None, radius: float) -> None:
    cmap = matplotlib.colormaps["plasma"]
    vmax = float(values.max()) if values.size and values.max() > 0 else 1.0
    colours = [cmap(v / vmax) if v > 0 else (0.75, 0.75, 0.75, 0.35) for v in values]
    if polygons is not None:
        polys = [np.asarray(p, float) @ rot.T + pos for p in polygons]
        ax.add_collection3d(Poly3DCollection(polys, facecolors=colours, edgecolors="k",
                                             linewidths=0.3, alpha=0.55, zorder=4))
    elif normals is not None:
        centres = np.asarray(normals, float) @ rot.T * radius + pos
        ax.scatter(centres[:, 0], centres[:, 1], centres[:, 2], s=60, c=colours,
                   edgecolors="k", linewidths=0.4, depthshade=False, zorder=4)


def _markers(ax: Axes, start: Vec, goal: Vec, pos: Vec, rot: np.ndarray, *,
             three_d: bool) -> None:
    for p, style, label in ((start, dict(marker="o", color="lime", ms=8), "start"),
                            (goal, dict(marker="*", color="red", ms=13), "goal"),
                            (pos, dict(marker="^", color="blue", ms=8), "UAV")):
        if p is None:
            continue
        p = np.asarray(p, float).reshape(-1, 3)  # one point, or one per episode
        coords = (p[:, 0], p[:, 1], p[:, 2]) if three_d else (p[:, 0], p[:, 1])
        ax.plot(*coords, linestyle="none", mec="k", label=label, **style)
    if pos is not None:
        fwd = rot[:, 0] * 2.0
        if three_d:
            ax.quiver(pos[0], pos[1], pos[2], fwd[0], fwd[1], fwd[2], color="blue", lw=1.2)
        else:
            ax.arrow(pos[0], pos[1], fwd[0], fwd[1], color="blue", width=0.12,
                     length_includes_head=True)
    if not three_d and any(p is not None for p in (start, goal, pos)):
        ax.legend(loc="upper right", fontsize=7, framealpha=0.8)


def _box_corners(box: np.ndarray) -> np.ndarray:
    """(8,3) corners of a yawed box (cx, cy, cz, hx, hy, hz, cos, sin); bottom four first."""
    cx, cy, cz, hx, hy, hz, c, s = box
    out = []
    for sz in (-1, 1):
        for sy in (-1, 1):
            for sx in (-1, 1):
                lx, ly = sx * hx, sy * hy
                out.append((cx + c * lx - s * ly, cy + s * lx + c * ly, cz + sz * hz))
    return np.array(out)


def _hull_2d(pts: np.ndarray) -> np.ndarray:
    """Convex hull (monotone chain), closed polygon of the (N,2) points."""
    p = np.unique(np.round(pts, 9), axis=0)
    if len(p) < 3:
        return p
    p = p[np.lexsort((p[:, 1], p[:, 0]))]

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[np.ndarray] = []
    for q in p:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], q) <= 0:
            lower.pop()
        lower.append(q)
    upper: list[np.ndarray] = []
    for q in p[::-1]:
        while len(upper) >= 2 and cross(upper[-2], upper[-1], q) <= 0:
            upper.pop()
        upper.append(q)
    hull = np.array(lower[:-1] + upper[:-1])
    return np.vstack([hull, hull[:1]])
