"""Fast video frames of an episode (pure numpy): a shaded top-down map and a side panel.

The env's ``render_mode="rgb_array"`` draws with this module (``sitl.render.scene`` is the
matplotlib picture of ``skyloop render``; about 1 s a frame). :class:`FastRenderer`
does the expensive part once per world and the rest per frame:

Once (``FastRenderer(world)``, tens of milliseconds): the map, north up, of the
navigable area plus a small pad. Terrain coloured by height (green lowlands, tan and
brown slopes), hillshaded from the north-west, with the flight-level contour in crimson
and a light hatch where the terrain rises above the flight level; buildings (grey roofs)
and tree crowns (green cones) from their half-spaces, with cast shadows and outlines;
the margin outside the navigable area dimmed; the aircraft loops dotted; a 5 m scale
bar and a north arrow. The side panel's static parts: two hemisphere charts of the 32
icosahedron faces (the Voronoi cells of the face normals seen from above), and the
frames of the altitude and distance strip charts with their reference lines.

Per frame (about a millisecond at 640x480): the base is copied; on the map the start,
the goal with its acceptance circle, the flown trail (dark outline, cyan core), the
LiDAR returns (coloured by range, red near to yellow far), the aircraft at time ``t``
(yawed boxes, orange when within 1 m of the vehicle's altitude, navy otherwise), a ring
at the icosahedron's radius whose horizontal sectors take the colour of the face that
looks that way, the velocity (one second ahead) and the quadrotor icon turned to its
heading (red front rotors); a border in the outcome's colour when the episode ended.
In the panel: scenario and step, the face charts coloured by value, the altitude trace
over the terrain under the trail, the distance to the goal, and a status line. Text is
a 3x5 bitmap font (upper case, digits and a few signs).
"""

from __future__ import annotations

import math

import numpy as np

from bus.task import TASK
from sitl.world.world import World

__all__ = ["FastRenderer"]

# --- colours ----------------------------------------------------------------------

_TERRAIN_STOPS = np.array([  # fraction of the height scale -> RGB
    (0.00, 62, 120, 72), (0.15, 104, 156, 88), (0.32, 168, 184, 112),
    (0.50, 196, 172, 122), (0.70, 158, 122, 88), (0.88, 140, 126, 118),
    (1.00, 236, 236, 232)], float)
_RANGE_STOPS = np.array([  # LiDAR range fraction: near red -> far yellow
    (0.0, 215, 25, 28), (0.5, 253, 141, 60), (1.0, 255, 240, 90)], float)
_FACE_STOPS = np.array([  # face value fraction (more = nearer obstacle): yellow -> dark red
    (0.0, 255, 230, 80), (0.4, 250, 150, 40), (0.7, 225, 50, 40), (1.0, 130, 0, 40)], float)
BUILDING = np.array([150, 152, 160], float)
CROWN = np.array([52, 120, 58], float)
TRUNK = np.array([110, 75, 40], float)
OTHER = np.array([128, 128, 128], float)
FREE_FACE = np.array([88, 94, 104], np.uint8)
PANEL_BG = np.array([28, 32, 38], np.uint8)
CHART_BG = np.array([40, 46, 54], np.uint8)
GRID = np.array([62, 70, 80], np.uint8)
TEXT = np.array([225, 230, 235], np.uint8)
DIM_TEXT = np.array([150, 158, 168], np.uint8)
CONTOUR = np.array([200, 30, 55], np.uint8)
TRAIL = np.array([40, 230, 255], np.uint8)
OUTLINE = np.array([15, 20, 25], np.uint8)
GOAL = np.array([230, 30, 40], np.uint8)
START = np.array([60, 220, 80], np.uint8)
AIRCRAFT = np.array([35, 50, 130], np.uint8)
AIRCRAFT_NEAR = np.array([255, 120, 0], np.uint8)
LOOP = np.array([40, 55, 140], np.uint8)
VEHICLE = np.array([245, 245, 245], np.uint8)
FRONT = np.array([235, 45, 45], np.uint8)
OUTCOME = {"success": np.array([60, 220, 80], np.uint8),
           "collision": np.array([235, 40, 40], np.uint8),
           "timeout": np.array([250, 180, 40], np.uint8)}
STATUS = {None: "FLYING", "success": "GOAL", "collision": "COLLISION", "timeout": "TIMEOUT"}

SUN_AZIMUTH, SUN_ELEVATION = math.radians(315.0), math.radians(45.0)  # light from the NW
SHADOW_ELEVATION = math.radians(58.0)  # steeper for shadows: shorter, less clutter

# --- a 3x5 bitmap font --------------------------------------------------------------

_FONT_ROWS = {
    "0": "111 101 101 101 111", "1": "010 110 010 010 111", "2": "111 001 111 100 111",
    "3": "111 001 011 001 111", "4": "101 101 111 001 001", "5": "111 100 111 001 111",
    "6": "111 100 111 101 111", "7": "111 001 010 010 010", "8": "111 101 111 101 111",
    "9": "111 101 111 001 111", "A": "010 101 111 101 101", "B": "110 101 110 101 110",
    "C": "011 100 100 100 011", "D": "110 101 101 101 110", "E": "111 100 110 100 111",
    "F": "111 100 110 100 100", "G": "011 100 101 101 011", "H": "101 101 111 101 101",
    "I": "111 010 010 010 111", "J": "001 001 001 101 010", "K": "101 110 100 110 101",
    "L": "100 100 100 100 111", "M": "101 111 111 101 101", "N": "110 101 101 101 101",
    "O": "010 101 101 101 010", "P": "110 101 110 100 100", "Q": "010 101 101 110 011",
    "R": "110 101 110 101 101", "S": "011 100 010 001 110", "T": "111 010 010 010 010",
    "U": "101 101 101 101 111", "V": "101 101 101 101 010", "W": "101 101 111 111 101",
    "X": "101 101 010 101 101", "Y": "101 101 010 010 010", "Z": "111 001 010 100 111",
    " ": "000 000 000 000 000", ".": "000 000 000 000 010", "/": "001 001 010 100 100",
    ":": "000 010 000 010 000", "-": "000 000 111 000 000", "+": "000 010 111 010 000",
    "%": "101 001 010 100 101", "(": "010 100 100 100 010", ")": "010 001 001 001 010",
}
FONT = {ch: np.array([[c == "1" for c in row] for row in rows.split()], bool)
        for ch, rows in _FONT_ROWS.items()}


def text_width(s: str, scale: int) -> int:
    """Width in pixels of ``s`` drawn by :func:`draw_text` at ``scale``."""
    return max(len(s) * 4 * scale - scale, 0)


def draw_text(img: np.ndarray, x: int, y: int, s: str, colour: np.ndarray,
              scale: int = 2) -> None:
    """Draw ``s`` (upper-cased; unknown characters as blanks) with its top-left at (x, y)."""
    for k, ch in enumerate(s.upper()):
        glyph = _glyph(ch, scale)
        if glyph is not None:
            _paint_mask(img, y, x + k * 4 * scale, glyph, colour)


_GLYPHS: dict[tuple[str, int], np.ndarray | None] = {}


def _glyph(ch: str, scale: int) -> np.ndarray | None:
    """The bitmap of ``ch`` scaled up ``scale`` times (None when blank or unknown), cached."""
    key = (ch, scale)
    if key not in _GLYPHS:
        glyph = FONT.get(ch)
        _GLYPHS[key] = (None if glyph is None or not glyph.any()
                        else np.kron(glyph, np.ones((scale, scale), bool)))
    return _GLYPHS[key]


# --- raster primitives ---------------------------------------------------------------

def _lut(stops: np.ndarray, n: int = 256) -> np.ndarray:
    """(n, 3) uint8 colour table interpolated between ``stops`` (fraction, r, g, b)."""
    f = np.linspace(0.0, 1.0, n)
    return np.stack([np.interp(f, stops[:, 0], stops[:, i]) for i in (1, 2, 3)],
                    axis=1).round().astype(np.uint8)


def _paint_mask(img: np.ndarray, r0: int, c0: int, mask: np.ndarray, colour: np.ndarray,
                alpha: float = 1.0) -> None:
    """Paint ``colour`` where ``mask`` (placed with its top-left at r0, c0) is set, clipped."""
    h, w = mask.shape
    r1, c1 = min(r0 + h, img.shape[0]), min(c0 + w, img.shape[1])
    rr0, cc0 = max(r0, 0), max(c0, 0)
    if rr0 >= r1 or cc0 >= c1:
        return
    m = mask[rr0 - r0:r1 - r0, cc0 - c0:c1 - c0]
    win = img[rr0:r1, cc0:c1]
    if alpha >= 1.0:
        win[m] = colour
    else:
        win[m] = (win[m] * (1.0 - alpha) + np.asarray(colour, float) * alpha).astype(np.uint8)


def _disc(img: np.ndarray, cx: float, cy: float, r: float, colour: np.ndarray,
          alpha: float = 1.0, inner: float = -1.0) -> None:
    """Fill the disc (or the ring ``inner`` < d <= ``r``) of radius r px centred at (cx, cy)."""
    r0, c0 = int(math.floor(cy - r)), int(math.floor(cx - r))
    n = int(math.ceil(2 * r)) + 2
    yy, xx = np.ogrid[r0:r0 + n, c0:c0 + n]
    d2 = (xx + 0.5 - cx) ** 2 + (yy + 0.5 - cy) ** 2
    mask = d2 <= r * r
    if inner >= 0:
        mask &= d2 > inner * inner
    _paint_mask(img, r0, c0, mask, colour, alpha)


def _polygon(img: np.ndarray, verts: np.ndarray, colour: np.ndarray,
             alpha: float = 1.0) -> None:
    """Fill the convex polygon with (K, 2) vertices (col, row) in pixels, any winding."""
    v = np.asarray(verts, float)
    area = np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1])
    if area < 0:
        v = v[::-1]
    c0, r0 = np.floor(v.min(0)).astype(int)
    c1, r1 = np.ceil(v.max(0)).astype(int) + 1
    yy, xx = np.mgrid[r0:r1, c0:c1] + 0.5
    mask = np.ones(yy.shape, bool)
    for a, b in zip(v, np.roll(v, -1, axis=0), strict=True):
        mask &= (b[0] - a[0]) * (yy - a[1]) - (b[1] - a[1]) * (xx - a[0]) >= 0
    _paint_mask(img, r0, c0, mask, colour, alpha)


def _line_samples(pts: np.ndarray, step: float = 0.5, dash: float = 0.0) -> np.ndarray:
    """(M, 2) points every ``step`` px along the polyline (N, 2); dashes of ``dash`` px."""
    pts = np.asarray(pts, float)
    if len(pts) == 1:
        return pts.copy()
    seg = np.diff(pts, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    n = np.maximum(np.ceil(length / step).astype(int), 1)
    idx = np.repeat(np.arange(len(seg)), n)
    start = np.cumsum(n) - n
    f = (np.arange(n.sum()) - np.repeat(start, n)) / np.repeat(n, n)
    out = pts[idx] + seg[idx] * f[:, None]
    if dash > 0:
        arc = np.concatenate([[0.0], np.cumsum(length)])[idx] + length[idx] * f
        out = out[(arc // dash) % 2 == 0]
    return np.vstack([out, pts[-1:]])


def _splat(img: np.ndarray, cols: np.ndarray, rows: np.ndarray, colour: np.ndarray,
           width: int = 1) -> None:
    """Set ``width`` x ``width`` squares at the (col, row) points (colour (3,) or (N, 3))."""
    ci = np.floor(np.asarray(cols, float)).astype(np.intp)
    ri = np.floor(np.asarray(rows, float)).astype(np.intp)
    colour = np.asarray(colour)
    lo = -(width // 2)
    hi = lo + width - 1
    ok = (ri + lo >= 0) & (ri + hi < img.shape[0]) & (ci + lo >= 0) & (ci + hi < img.shape[1])
    if not ok.all():  # squares that would cross the border are left out
        ri, ci = ri[ok], ci[ok]
        colour = colour if colour.ndim == 1 else colour[ok]
    for dr in range(lo, hi + 1):
        for dc in range(lo, hi + 1):
            img[ri + dr, ci + dc] = colour


def _polyline(img: np.ndarray, pts: np.ndarray, colour: np.ndarray, width: int = 1,
              dash: float = 0.0) -> None:
    """Draw the polyline through the (N, 2) (col, row) pixel points."""
    if len(pts) == 0:
        return
    s = _line_samples(pts, 0.5, dash)
    _splat(img, s[:, 0], s[:, 1], colour, width)


# --- the renderer ----------------------------------------------------------------------

class FastRenderer:
    """Frames of episodes in one world; build once per world, then call :meth:`frame`.

    ``face_normals`` (32, 3), in the body frame, are the icosahedron's (the face charts
    and the map's face ring are drawn only with them); ``face_scale`` is the face value
    drawn darkest (the radius for the "distance" encoding, 1 for "proximity"). The
    strip charts span ``max_steps`` control steps; ``goal_radius`` and
    ``goal_max_altitude`` are drawn as reference lines (defaults: ``bus.task.TASK``'s).
    """

    def __init__(self, world: World, size: tuple[int, int] = (640, 480), *,
                 face_normals: np.ndarray | None = None,
                 face_scale: float = TASK.ico_radius, ico_radius: float = TASK.ico_radius,
                 max_steps: int = TASK.max_steps, goal_radius: float = TASK.goal_radius,
                 goal_max_altitude: float = TASK.goal_max_altitude,
                 lidar_range: float = 4.5, pad: float = 2.5) -> None:
        width, height = int(size[0]), int(size[1])
        if height < 160 or width - height < 120:
            raise ValueError(f"size must leave a side panel: width >= height + 120 and "
                             f"height >= 160, got {size}")
        self.world = world
        self._key = (id(world), id(world.packed))
        self.size = (width, height)
        self.face_normals = None if face_normals is None else np.asarray(face_normals, float)
        self.face_scale = float(face_scale)
        self.ico_radius = float(ico_radius)
        self.max_steps = max(int(max_steps), 1)
        self.goal_radius = float(goal_radius)
        self.goal_max_altitude = float(goal_max_altitude)
        self.lidar_range = float(lidar_range)
        self.scenario = world.scenario.name
        # map: a square of side `height` px, north up
        xmin, xmax, ymin, ymax = world.bounds
        span = max(xmax - xmin, ymax - ymin) + 2 * pad
        cx, cy = (xmin + xmax) / 2, (ymin + ymax) / 2
        self.view = (cx - span / 2, cx + span / 2, cy - span / 2, cy + span / 2)
        self.map_px = height
        self.scale = height / span  # px per metre
        self.panel_x = height
        self.font = 2 if width - height >= 150 else 1
        self._range_lut = _lut(_RANGE_STOPS)
        self._face_lut = _lut(_FACE_STOPS)
        self.base = np.empty((height, width, 3), np.uint8)
        self.base[:, :height] = self._map_base()
        self.base[:, height:] = PANEL_BG
        self._panel_layout()
        self._ring_setup()
        self._scratch = np.zeros(height * height, np.intp)  # per-pixel winner of the points

    def matches(self, world: World) -> bool:
        """True if this renderer's precomputed map is that of ``world`` as it is now."""
        return self._key == (id(world), id(world.packed))

    # -- coordinates ---------------------------------------------------------------

    def to_px(self, xy: np.ndarray) -> np.ndarray:
        """World (x east, y north) metres -> map pixels (col, row), floats."""
        xy = np.asarray(xy, float)
        x0, _, _, y1 = self.view
        return np.stack([(xy[..., 0] - x0) * self.scale, (y1 - xy[..., 1]) * self.scale],
                        axis=-1)

    # -- once per world ------------------------------------------------------------

    def _map_base(self) -> np.ndarray:
        """The static map: shaded terrain, obstacles with shadows, contour, loops, legend."""
        w = self.world
        n = self.map_px
        x0, _, _, y1 = self.view
        xs = x0 + (np.arange(n) + 0.5) / self.scale
        ys = y1 - (np.arange(n) + 0.5) / self.scale
        gx, gy = np.meshgrid(xs, ys)
        terrain = np.asarray(w.terrain_height(gx, gy), float)
        top = terrain.copy()
        solid_id = np.full((n, n), -1, np.int32)
        kinds = []
        for k, s in enumerate(w.solids):
            kinds.append(s.kind)
            self._raster_solid(s.planes, s.vertices, gx, gy, top, solid_id, k)
        # colours: terrain by height, solids by kind
        fl = w.flight_level
        vmax = max(fl * 2.5, float(w.terrain.heights.max()), 1.0)
        vmin = min(0.0, float(w.terrain.heights.min()))
        frac = np.clip((terrain - vmin) / (vmax - vmin), 0.0, 1.0)
        rgb = _lut(_TERRAIN_STOPS)[(frac * 255).astype(np.intp)].astype(float)
        on_solid = solid_id >= 0
        if on_solid.any():
            table = np.array([{"building": BUILDING, "crown": CROWN, "trunk": TRUNK}
                              .get(kind, OTHER) for kind in kinds])
            rgb[on_solid] = table[solid_id[on_solid]]
            roof = on_solid & (np.array([kind == "building" for kind in kinds] + [False])
                               [solid_id])
            # taller buildings slightly lighter
            rise = np.clip((top - terrain) / 15.0, 0.0, 1.0)
            rgb[roof] *= (0.85 + 0.3 * rise[roof])[:, None]
        # hillshade of the composite surface
        px = 1.0 / self.scale
        dzdy_rows, dzdx = np.gradient(top, px)
        dzdy = -dzdy_rows  # rows run south
        light = np.array([math.cos(SUN_ELEVATION) * math.sin(SUN_AZIMUTH),
                          math.cos(SUN_ELEVATION) * math.cos(SUN_AZIMUTH),
                          math.sin(SUN_ELEVATION)])
        shade = (-dzdx * light[0] - dzdy * light[1] + light[2]) / np.sqrt(
            1.0 + dzdx**2 + dzdy**2)
        factor = 0.35 + 0.65 * np.clip(shade, 0.0, 1.0) / light[2]
        rgb *= np.clip(factor, 0.3, 1.35)[..., None]
        rgb[self._shadow(top)] *= 0.62
        # terrain above the flight level: a light diagonal hatch; the flight-level contour
        rr, cc = np.mgrid[0:n, 0:n]
        above = (terrain > fl) & ~on_solid
        rgb[above & ((rr + cc) % 7 == 0)] *= 0.78
        # outlines of obstacles
        edge = np.zeros((n, n), bool)
        edge[:, 1:] |= solid_id[:, 1:] != solid_id[:, :-1]
        edge[1:, :] |= solid_id[1:, :] != solid_id[:-1, :]
        rgb[edge] *= 0.55
        # navigable area: margin dimmed, a dark frame
        xmin, xmax, ymin, ymax = w.bounds
        outside = (gx < xmin) | (gx > xmax) | (gy < ymin) | (gy > ymax)
        grey = rgb[outside].mean(axis=1, keepdims=True)
        rgb[outside] = (0.55 * rgb[outside] + 0.45 * grey) * 0.7
        img = np.clip(rgb, 0, 255).astype(np.uint8)
        up = terrain > fl
        contour = np.zeros((n, n), bool)
        contour[:, 1:] |= up[:, 1:] != up[:, :-1]
        contour[1:, :] |= up[1:, :] != up[:-1, :]
        img[contour & ~on_solid] = CONTOUR
        frame = self.to_px(np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax],
                                     [xmin, ymin]]))
        _polyline(img, frame, OUTLINE, 1)
        for k in range(len(w.fleet)):  # aircraft loops
            loop = w.fleet.waypoints[k, : w.fleet.count[k], :2]
            _polyline(img, self.to_px(loop), LOOP, 1, dash=4.0)
        self._legend(img)
        return img

    def _raster_solid(self, planes: np.ndarray, vertices: np.ndarray, gx: np.ndarray,
                      gy: np.ndarray, top: np.ndarray, solid_id: np.ndarray, k: int) -> None:
        """Raise ``top`` to the solid's upper surface where its column is seen from above."""
        lo, hi = self.to_px(vertices[:, :2]).min(0), self.to_px(vertices[:, :2]).max(0)
        c0, r0 = max(int(lo[0]) - 1, 0), max(int(lo[1]) - 1, 0)
        c1, r1 = min(int(hi[0]) + 2, self.map_px), min(int(hi[1]) + 2, self.map_px)
        if c0 >= c1 or r0 >= r1:
            return
        x, y = gx[r0:r1, c0:c1], gy[r0:r1, c0:c1]
        upper = np.full(x.shape, np.inf)
        lower = np.full(x.shape, -np.inf)
        inside = np.ones(x.shape, bool)
        for nx, ny, nz, d in planes:
            a = d - nx * x - ny * y
            if nz > 1e-9:
                np.minimum(upper, a / nz, out=upper)
            elif nz < -1e-9:
                np.maximum(lower, a / nz, out=lower)
            else:
                inside &= a >= -1e-9
        inside &= (upper >= lower) & np.isfinite(upper)
        win_top, win_id = top[r0:r1, c0:c1], solid_id[r0:r1, c0:c1]
        seen = inside & (upper > win_top)
        win_top[seen] = upper[seen]
        win_id[seen] = k

    def _shadow(self, top: np.ndarray) -> np.ndarray:
        """Pixels in the shadow of higher ground or obstacles toward the light (NW)."""
        drop = math.sqrt(2.0) / self.scale * math.tan(SHADOW_ELEVATION)
        s = top.copy()
        for r in range(1, s.shape[0]):  # the light's ray falls one diagonal pixel a row
            np.maximum(s[r, 1:], s[r - 1, :-1] - drop, out=s[r, 1:])
        return s > top + 0.05

    def _legend(self, img: np.ndarray) -> None:
        """A 5 m scale bar (bottom left) and a north arrow (top left) on the map."""
        n, f = self.map_px, self.font
        bar = 5.0 * self.scale
        x0, y0 = 10, n - 14
        img[y0:y0 + 3, x0:int(x0 + bar)] = OUTLINE
        img[y0 + 1, x0 + 1:int(x0 + bar) - 1] = VEHICLE
        draw_text(img, int(x0 + bar) + 5, y0 - 2 * f + 1, "5 M", OUTLINE, f)
        _polygon(img, np.array([[16.0, 8.0], [10.0, 24.0], [22.0, 24.0]]), OUTLINE)
        draw_text(img, 10 + 6 - (3 * f) // 2, 28, "N", OUTLINE, f)

    def _panel_layout(self) -> None:
        """Places of the panel's parts; draws their static frames into the base."""
        width, height = self.size
        pw, f = width - self.panel_x, self.font
        line = 7 * f  # text line height
        x = self.panel_x
        y = 6
        self._title_y = y
        y += line + 2
        self._progress = (x + 8, y, pw - 16)
        y += 8
        # face charts: two hemispheres side by side
        label_h = line
        radius = max(min((pw - 24) // 4, (height // 5) // 2), 12)
        cy = y + label_h + radius
        self._hemi = [(x + pw // 4, cy, radius, 1.0), (x + 3 * pw // 4, cy, radius, -1.0)]
        draw_text(self.base, x + 8, y, "FACES", DIM_TEXT, f)
        self._face_cells = []
        for hx, hy, r, sign in self._hemi:
            self._face_cells.append(self._hemisphere(hx, hy, r, sign))
            lab = "UP" if sign > 0 else "DOWN"
            draw_text(self.base, hx - text_width(lab, f) // 2, hy + r + 4, lab, DIM_TEXT, f)
        y = cy + radius + 4 + line + 6
        # two strip charts share what is left above the status line
        status_h = 2 * line + 8
        avail = height - y - status_h
        chart_h = (avail - 2 * (line + 4)) // 2
        self._charts = {}
        for name in ("alt", "dist"):
            y += line + 2
            box = (x + 8, y, pw - 16, chart_h)
            self.base[y:y + chart_h, x + 8:x + pw - 8] = CHART_BG
            self._charts[name] = box
            y += chart_h + 4
        self._status_y = y + 2
        # altitude chart: 0 .. alt_max with flight level and goal altitude lines
        fl = self.world.flight_level
        self.alt_max = max(self.goal_max_altitude * 1.4, fl * 2.5, 1.0)
        self._hline("alt", fl / self.alt_max, CONTOUR, dash=3)
        self._hline("alt", self.goal_max_altitude / self.alt_max, GRID, dash=0)
        sg = self.world.scenario.start_goal
        self.dist_max = max(sg.max_distance * 1.15, 5.0)
        self._hline("dist", self.goal_radius / self.dist_max, GOAL, dash=3)
        for k in range(1, 4):  # quarter-time ticks
            for name in ("alt", "dist"):
                bx, by, bw, bh = self._charts[name]
                self.base[by:by + bh:3, bx + k * bw // 4] = GRID

    def _hline(self, chart: str, frac: float, colour: np.ndarray, dash: int) -> None:
        """A horizontal reference line at ``frac`` of a strip chart's height."""
        bx, by, bw, bh = self._charts[chart]
        if not 0.0 <= frac <= 1.0:
            return
        r = by + bh - 1 - int(round(frac * (bh - 1)))
        cols = np.arange(bx, bx + bw)
        if dash:
            cols = cols[(cols - bx) // dash % 2 == 0]
        self.base[r, cols] = colour

    def _hemisphere(self, cx: int, cy: int, r: int, sign: float) -> tuple:
        """Face index of every pixel of a hemisphere chart (azimuthal equidistant, forward
        up, left to the left), and the cells' borders drawn into the base."""
        yy, xx = np.mgrid[cy - r:cy + r + 1, cx - r:cx + r + 1]
        u, v = (xx - cx) / r, (yy - cy) / r
        rho = np.hypot(u, v)
        inside = rho <= 1.0
        theta = rho * math.pi / 2  # from the pole
        with np.errstate(invalid="ignore", divide="ignore"):
            fwd = np.where(rho > 0, -v / rho, 1.0)
            left = np.where(rho > 0, -u / rho, 0.0)
        dirs = np.stack([np.sin(theta) * fwd, np.sin(theta) * left, sign * np.cos(theta)], -1)
        if self.face_normals is None:
            idx = np.zeros(rho.shape, np.intp)
        else:
            idx = np.argmax(dirs @ self.face_normals.T, axis=-1)
        border = np.zeros(rho.shape, bool)
        border[:, 1:] |= idx[:, 1:] != idx[:, :-1]
        border[1:, :] |= idx[1:, :] != idx[:-1, :]
        border |= (rho > 1.0 - 1.5 / r) & inside
        rows, cols = yy[inside], xx[inside]
        self.base[rows, cols] = FREE_FACE
        self.base[yy[border & inside], xx[border & inside]] = PANEL_BG
        keep = inside & ~border
        # forward tick above the chart
        self.base[cy - r - 4:cy - r - 1, cx - 1:cx + 1] = DIM_TEXT
        return yy[keep], xx[keep], idx[keep]

    def _ring_setup(self) -> None:
        """Pixel offsets of the map ring at the icosahedron's radius and the face each
        body azimuth (720 bins) looks at."""
        r = self.ico_radius * self.scale
        n = int(math.ceil(r)) + 3
        dy, dx = np.mgrid[-n:n + 1, -n:n + 1]
        d = np.hypot(dx, dy)
        keep = (d >= r - 1.5) & (d <= r + 1.5)
        self._ring_dx, self._ring_dy = dx[keep], dy[keep]
        self._ring_az = np.arctan2(-dy[keep], dx[keep])  # world azimuth, rows run south
        if self.face_normals is not None:
            az = np.linspace(0, 2 * math.pi, 720, endpoint=False)
            dirs = np.stack([np.cos(az), np.sin(az), np.zeros_like(az)], -1)
            self._ring_face = np.argmax(dirs @ self.face_normals.T, axis=-1)

    # -- per frame -----------------------------------------------------------------

    def frame(self, *, position: np.ndarray, rotation: np.ndarray | None = None,
              path: np.ndarray | None = None, start: np.ndarray | None = None,
              goal: np.ndarray | None = None, points: np.ndarray | None = None,
              face_values: np.ndarray | None = None, velocity: np.ndarray | None = None,
              t: float = 0.0, step: int = 0, outcome: str | None = None) -> np.ndarray:
        """One RGB uint8 frame (height, width, 3) of the vehicle at ``position``.

        ``rotation`` maps the body (FLU) to the world (ENU); ``points`` are LiDAR
        returns in the body/sensor frame; ``path`` is the (T, 3) trail flown so far;
        ``t`` is the time at which aircraft are drawn; ``outcome`` (``success``,
        ``collision``, ``timeout`` or None) colours the map's border and the status.
        """
        img = self.base.copy()
        pos = np.asarray(position, float)
        rot = np.eye(3) if rotation is None else np.asarray(rotation, float)
        yaw = math.atan2(rot[1, 0], rot[0, 0])
        mapv = img[:, : self.map_px]
        if start is not None:
            c = self.to_px(np.asarray(start, float)[:2])
            _disc(mapv, c[0], c[1], 6, OUTLINE)
            _disc(mapv, c[0], c[1], 5, START, inner=2.5)
        if goal is not None:
            self._draw_goal(mapv, np.asarray(goal, float))
        path_arr = None if path is None else np.asarray(path, float).reshape(-1, 3)
        if path_arr is not None and len(path_arr) > 1:
            px = self.to_px(path_arr[:, :2])
            _polyline(mapv, px, OUTLINE, 4)
            _polyline(mapv, px, TRAIL, 2)
        self._draw_aircraft(mapv, t, float(pos[2]))
        if points is not None and len(points):
            self._draw_points(mapv, np.asarray(points, float), pos, rot)
        if face_values is not None and self.face_normals is not None:
            self._draw_face_ring(mapv, pos, yaw, np.asarray(face_values, float))
        if velocity is not None:
            v = np.asarray(velocity, float)
            a, b = self.to_px(pos[:2]), self.to_px(pos[:2] + v[:2])
            _polyline(mapv, np.array([a, b]), OUTLINE, 3)
            _polyline(mapv, np.array([a, b]), VEHICLE, 1)
        self._draw_vehicle(mapv, pos, yaw)
        if outcome in OUTCOME:
            colour = OUTCOME[outcome]
            mapv[:4], mapv[-4:], mapv[:, :4], mapv[:, -4:] = colour, colour, colour, colour
        self._draw_panel(img, pos, path_arr, goal, face_values, velocity, step, outcome)
        return img

    def _draw_goal(self, img: np.ndarray, goal: np.ndarray) -> None:
        """The goal: its acceptance circle (translucent) and a red-white target."""
        c = self.to_px(goal[:2])
        r = self.goal_radius * self.scale
        _disc(img, c[0], c[1], r, GOAL, alpha=0.18)
        _disc(img, c[0], c[1], r, GOAL, inner=r - 1.2)
        _disc(img, c[0], c[1], 8, OUTLINE)
        _disc(img, c[0], c[1], 7, GOAL)
        _disc(img, c[0], c[1], 4.5, VEHICLE)
        _disc(img, c[0], c[1], 2.2, GOAL)

    def _draw_aircraft(self, img: np.ndarray, t: float, z: float) -> None:
        """Aircraft at time t as yawed boxes; orange when within 1 m of altitude z."""
        boxes = self.world.aircraft_boxes(t)
        for cx, cy, cz, hx, hy, _, c, s in boxes:
            corners = np.array([[cx + c * sx * hx - s * sy * hy, cy + s * sx * hx + c * sy * hy]
                                for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
            px = self.to_px(corners)
            near = abs(cz - z) <= 1.0
            centre = px.mean(0)
            _polygon(img, centre + (px - centre) * 1.0 + 1.5, OUTLINE)
            _polygon(img, px, AIRCRAFT_NEAR if near else AIRCRAFT)
            nose = self.to_px(np.array([cx + c * hx * 1.3, cy + s * hx * 1.3]))
            _polyline(img, np.array([centre, nose]), VEHICLE, 2)

    def _draw_points(self, img: np.ndarray, points: np.ndarray, pos: np.ndarray,
                     rot: np.ndarray) -> None:
        """LiDAR returns in the world, 2x2 px, red near to yellow far (far drawn first)."""
        rng = np.linalg.norm(points, axis=1)
        ok = np.isfinite(rng)
        points, rng = points[ok], rng[ok]
        order = np.argsort(-rng)
        world = points[order] @ rot.T + pos
        px = np.floor(self.to_px(world[:, :2])).astype(np.intp)
        n = self.map_px
        inside = (px[:, 0] >= 0) & (px[:, 0] < n) & (px[:, 1] >= 0) & (px[:, 1] < n)
        px, rng = px[inside], rng[order][inside]
        # one point a pixel, the nearest (drawn last) wins: most of a scan overlaps
        flat = px[:, 1] * n + px[:, 0]
        k = np.arange(len(flat))
        self._scratch[flat] = k
        top = self._scratch[flat] == k
        frac = np.clip(rng[top] / max(self.lidar_range, 1e-6), 0.0, 1.0)
        _splat(img, px[top, 0], px[top, 1], self._range_lut[(frac * 255).astype(np.intp)], 2)

    def _face_colours(self, values: np.ndarray) -> np.ndarray:
        """(32, 3) colours of the faces: grey when free (0), yellow to dark red with value."""
        frac = np.clip(values / max(self.face_scale, 1e-9), 0.0, 1.0)
        out = self._face_lut[(frac * 255).astype(np.intp)]
        out[~(values > 0)] = FREE_FACE
        return out

    def _draw_face_ring(self, img: np.ndarray, pos: np.ndarray, yaw: float,
                        values: np.ndarray) -> None:
        """A ring at the icosahedron's radius: each sector in the colour of the face that
        looks that way horizontally (free faces faint)."""
        c = self.to_px(pos[:2])
        rows = np.floor(c[1]).astype(int) + self._ring_dy
        cols = np.floor(c[0]).astype(int) + self._ring_dx
        ok = (rows >= 0) & (rows < img.shape[0]) & (cols >= 0) & (cols < img.shape[1])
        body_az = (self._ring_az[ok] - yaw) % (2 * math.pi)
        face = self._ring_face[(body_az * (720 / (2 * math.pi))).astype(np.intp) % 720]
        occupied = values[face] > 0
        colours = self._face_colours(values)[face]
        rows, cols = rows[ok], cols[ok]
        win = img[rows, cols].astype(np.float32)
        alpha = np.where(occupied, 0.9, 0.25)[:, None]
        img[rows, cols] = (win * (1 - alpha) + colours * alpha).astype(np.uint8)

    def _draw_vehicle(self, img: np.ndarray, pos: np.ndarray, yaw: float) -> None:
        """The quadrotor (not to scale): arms in an X, four rotors, the front two red."""
        c = self.to_px(pos[:2])
        arm = 9.0
        for k, ang in enumerate((math.pi / 4, -math.pi / 4, 3 * math.pi / 4, -3 * math.pi / 4)):
            a = yaw + ang
            tip = c + arm * np.array([math.cos(a), -math.sin(a)])
            _polyline(img, np.array([c, tip]), OUTLINE, 3)
            _disc(img, tip[0], tip[1], 4.5, OUTLINE)
            _disc(img, tip[0], tip[1], 3.3, FRONT if k < 2 else VEHICLE)
        _disc(img, c[0], c[1], 4.0, OUTLINE)
        _disc(img, c[0], c[1], 2.8, VEHICLE)
        nose = c + 16.0 * np.array([math.cos(yaw), -math.sin(yaw)])
        _polyline(img, np.array([c, nose]), OUTLINE, 3)
        _polyline(img, np.array([c, nose]), FRONT, 1)

    def _chart_xy(self, name: str, values: np.ndarray, vmax: float) -> np.ndarray:
        """(N, 2) pixel points of a series (one value per step) in a strip chart."""
        bx, by, bw, bh = self._charts[name]
        k = np.arange(len(values))
        cols = bx + np.minimum(k, self.max_steps) * (bw - 1) / self.max_steps
        rows = by + bh - 1 - np.clip(values / vmax, 0.0, 1.0) * (bh - 1)
        return np.stack([cols, rows], -1)

    def _draw_panel(self, img: np.ndarray, pos: np.ndarray, path: np.ndarray | None,
                    goal: np.ndarray | None, face_values: np.ndarray | None,
                    velocity: np.ndarray | None, step: int, outcome: str | None) -> None:
        """The side panel: title and step, progress bar, face charts, altitude and distance
        charts with their current values, status and speed."""
        f = self.font
        x = self.panel_x
        pw = self.size[0] - x
        draw_text(img, x + 8, self._title_y, self.scenario, TEXT, f)
        label = f"{step}/{self.max_steps}"
        draw_text(img, x + pw - 8 - text_width(label, f), self._title_y, label, DIM_TEXT, f)
        px0, py0, plen = self._progress
        img[py0:py0 + 3, px0:px0 + plen] = GRID
        done = int(round(plen * min(step / self.max_steps, 1.0)))
        img[py0:py0 + 3, px0:px0 + done] = OUTCOME.get(outcome, TRAIL)
        if face_values is not None and self.face_normals is not None:
            colours = self._face_colours(np.asarray(face_values, float))
            for rows, cols, idx in self._face_cells:
                img[rows, cols] = colours[idx]
        if path is None or len(path) == 0:
            path = pos.reshape(1, 3)
        line = 7 * f
        # altitude: terrain under the trail (filled), the vehicle's altitude
        bx, by, bw, bh = self._charts["alt"]
        ground = np.asarray(self.world.terrain_height(path[:, 0], path[:, 1]), float)
        g = self._chart_xy("alt", ground, self.alt_max)
        cols = np.arange(bx, int(g[-1, 0]) + 1)
        if len(cols):
            tops = np.interp(cols, g[:, 0], g[:, 1]) if len(g) > 1 else np.full(len(cols),
                                                                                  g[0, 1])
            rows = np.arange(by, by + bh)[:, None]
            fill = rows >= np.round(tops)[None, :]
            win = img[by:by + bh, bx:bx + len(cols)]
            win[fill] = (0.5 * win[fill] + 0.5 * np.array([140, 110, 80])).astype(np.uint8)
        _polyline(img, self._chart_xy("alt", path[:, 2], self.alt_max), TRAIL, 2)
        draw_text(img, bx, by - line - 1, f"ALT {pos[2]:.1f} M", TEXT, f)
        # distance to the goal
        if goal is not None:
            dist = np.linalg.norm(path - np.asarray(goal, float), axis=1)
            bx, by, bw, bh = self._charts["dist"]
            _polyline(img, self._chart_xy("dist", dist, self.dist_max), VEHICLE, 2)
            draw_text(img, bx, by - line - 1, f"GOAL {dist[-1]:.1f} M", TEXT, f)
        # status and speed
        y = self._status_y
        colour = OUTCOME.get(outcome, TEXT)
        draw_text(img, x + 8, y, STATUS.get(outcome, str(outcome).upper()), colour, f)
        if velocity is not None:
            speed = float(np.linalg.norm(np.asarray(velocity, float)))
            draw_text(img, x + 8, y + line + 2, f"V {speed:.1f} M/S", DIM_TEXT, f)
