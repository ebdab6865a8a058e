"""World: terrain, obstacles, aircraft, collision, start/goal sampling, difficulty."""

from __future__ import annotations

import time
from functools import cache

import numpy as np
import pytest
from scipy import ndimage

from sitl.world.world import UAV_BODY_RADIUS, World


@cache
def world(name: str) -> World:
    return World(name)


def test_body_radius_from_f450() -> None:
    assert 0.1651 + 0.12 <= UAV_BODY_RADIUS <= 0.35


def test_geometry_fixed_by_seed() -> None:
    a, b = World("forest"), world("forest")
    assert np.array_equal(a.terrain.heights, b.terrain.heights)
    assert len(a.solids) == len(b.solids) > 10
    assert all(np.array_equal(s.vertices, t.vertices) for s, t in zip(a.solids, b.solids,
                                                                       strict=True))


def test_bounds_and_terrain_height() -> None:
    w = world("valley")
    assert w.flight_level == 3.5 and w.bounds == (-17.5, 17.5, -17.5, 17.5)
    t = w.terrain
    h = t.heights
    # at vertices the mesh height is the vertex height; on the diagonal it interpolates
    assert w.terrain_height(t.x0 + 3 * t.res, t.y0 + 5 * t.res) == pytest.approx(h[5, 3])
    mid = w.terrain_height(t.x0 + 3.5 * t.res, t.y0 + 5.5 * t.res)
    assert mid == pytest.approx((h[5, 3] + h[6, 4]) / 2)
    xs = np.linspace(-20, 20, 7)
    arr = w.terrain_height(xs, xs * 0.5)
    assert arr.shape == (7,)
    assert np.allclose(arr, [w.terrain_height(float(x), float(x) * 0.5) for x in xs])
    assert isinstance(w.terrain_height(1.0, 2.0), float)
    assert h.max() > 5.0  # hills rise above the flight level


@pytest.mark.parametrize("name", ["valley", "city"])
def test_scalar_terrain_height_is_the_array_one_bit_for_bit(name: str) -> None:
    """One point takes a pure-Python path (the sim asks every step): it must give the
    very same doubles as the vectorised path, inside, on vertices and past the edges."""
    t = world(name).terrain
    rng = np.random.default_rng(7)
    xmin, xmax, ymin, ymax = t.extent
    xs = np.concatenate([rng.uniform(xmin - 5, xmax + 5, 2000), t.x0 + np.arange(5) * t.res,
                         [xmin, xmax, xmax + 1e-9]])
    ys = np.concatenate([rng.uniform(ymin - 5, ymax + 5, 2000), t.y0 + np.arange(5) * t.res,
                         [ymax, ymin, ymin - 3.0]])
    arr = t.height(xs, ys)
    one = np.array([t.height(float(x), float(y)) for x, y in zip(xs, ys, strict=True)])
    assert np.array_equal(arr, one)


def test_terrain_collision() -> None:
    w = world("valley")
    x, y = 0.3, -0.7
    g = w.terrain_height(x, y)
    assert w.collides(np.array([x, y, g - 1.0]), 0.3, 0.0)  # underground
    assert w.collides(np.array([x, y, g + 0.25]), 0.3, 0.0)
    assert not w.collides(np.array([x, y, g + 0.6]), 0.3, 0.0)
    assert not w.collides(np.array([x, y, 40.0]), 0.3, 0.0)
    # beside a steep hill: the sphere touches the slope before its centre is above it
    i = np.unravel_index(np.argmax(w.terrain.heights), w.terrain.heights.shape)
    px, py = w.terrain.x0 + i[1] * w.terrain.res, w.terrain.y0 + i[0] * w.terrain.res
    for d in np.linspace(0.5, 8, 40):
        p = np.array([px + d, py, 3.5])
        if not w.collides(p, 0.3, 0.0):
            assert w.terrain_height(p[0] - 0.3, p[1]) < 3.5
            break


def test_box_collision_exact() -> None:
    w = world("city")
    b = next(s for s in w.solids if s.kind == "building").box
    cx, cy, cz, hx, hy, hz = b[:6]
    r = 0.3
    assert w.collides(np.array([cx, cy, cz]), r, 0.0)
    assert w.collides(np.array([cx + hx + r - 0.02, cy, 3.5]), r, 0.0)
    assert not w.collides(np.array([cx + hx + r + 0.02, cy, 3.5]), r, 0.0)
    # near a vertical edge: exact (distance to the edge), not the face-plane test
    d = (r + 0.02) / np.sqrt(2)
    assert not w.collides(np.array([cx + hx + d, cy + hy + d, 3.5]), r, 0.0)


def test_tree_collision() -> None:
    w = world("forest")
    crown = next(s for s in w.solids if s.kind == "crown")
    c = crown.vertices.mean(0)
    assert w.collides(c, UAV_BODY_RADIUS, 0.0)
    assert w.straight_line_blocked(c + [-10, 0, 0], c + [10, 0, 0], UAV_BODY_RADIUS)


def test_aircraft_move_and_collide() -> None:
    w = world("dynamic")
    assert len(world("valley").fleet) == 0
    p0, p1 = w.aircraft_positions(10.0), w.aircraft_positions(10.5)
    assert p0.shape == (3, 3)
    speeds = np.linalg.norm(p1 - p0, axis=1) / 0.5
    assert np.all((speeds > 0.9) & (speeds < 2.0))
    for k in range(3):
        p = p0[k]
        assert w.collides(p, 0.3, 10.0)
        assert not w.collides_static(p, 0.3)
        assert not w.collides(p, 0.3, 10.0 + 5.0)  # it has flown on
    zs = np.array([w.aircraft_positions(t)[:, 2] for t in np.linspace(0, 40, 200)])
    assert np.all(zs.min(0) < 3.5) and np.all(zs.max(0) > 3.5)


def test_aircraft_paths_stay_clear_of_static_geometry() -> None:
    w = world("dynamic")
    rad = w.fleet.bounding_radius()
    for t in np.linspace(0, 60, 600):
        for k, p in enumerate(w.aircraft_positions(t)):
            assert not w.collides_static(p, rad[k]), (k, t, p)


def test_collides_is_fast() -> None:
    w = world("dynamic")
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-17, 17, (2000, 2)), np.full(2000, 3.5)])
    w.collides(pts[0], 0.3, 0.0)
    t0 = time.perf_counter()
    for i, p in enumerate(pts):
        w.collides(p, 0.3, 0.1 * i)
    per_call = (time.perf_counter() - t0) / len(pts)
    assert per_call < 30e-6, f"{per_call * 1e6:.1f} us per call"


@pytest.mark.parametrize("name", ["valley", "forest", "city", "dynamic"])
def test_sample_start_goal(name: str) -> None:
    w = world(name)
    sg = w.scenario.start_goal
    labels, _ = ndimage.label(w.free)
    rng = np.random.default_rng(7)
    for _ in range(100):
        s, g = w.sample_start_goal(rng)
        assert s[2] == g[2] == w.flight_level
        assert sg.min_distance <= np.hypot(*(g - s)[:2]) <= sg.max_distance
        for p in (s, g):
            assert not w.collides(p, sg.clearance, 0.0)
            assert w.terrain_height(p[0], p[1]) <= sg.max_terrain_height
            assert w.bounds[0] <= p[0] <= w.bounds[1] and w.bounds[2] <= p[1] <= w.bounds[3]
        # solvable: start and goal are in the same connected free region
        cells = [(int((p[1] - w.bounds[2]) // w.terrain.res),
                  int((p[0] - w.bounds[0]) // w.terrain.res)) for p in (s, g)]
        assert labels[cells[0]] == labels[cells[1]] != 0
    a = World(name).sample_start_goal(np.random.default_rng(3))
    b = w.sample_start_goal(np.random.default_rng(3))
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("name", ["valley", "forest", "city", "dynamic"])
def test_straight_line_mostly_blocked_but_world_connected(name: str) -> None:
    w = world(name)
    assert w.connected_share >= 0.9
    assert 0.4 < w.free.mean() < 0.95  # obstacles cover a real share, much stays free
    rng = np.random.default_rng(2024)
    n = 200
    blocked = sum(w.straight_line_blocked(*w.sample_start_goal(rng), UAV_BODY_RADIUS)
                  for _ in range(n))
    assert blocked / n > 0.6, f"{name}: only {blocked / n:.0%} of straight lines blocked"


def test_straight_line_blocked_free_line() -> None:
    w = world("valley")
    assert not w.straight_line_blocked(np.array([0, 0, 30.0]), np.array([10, 5, 30.0]), 0.3)
