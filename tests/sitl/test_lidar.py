"""VLP-16 LiDAR against known geometry, for both ray-casting engines."""

from __future__ import annotations

import math
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from sitl.lidar.scanner import Lidar, LidarConfig
from sitl.world.obstacles import box_solid
from sitl.world.scenario import load_scenario
from sitl.world.world import World

ENGINES = ["numba", "embree"]
FLAT = """
name = "flat"
seed = 1
[area]
size_x = 40.0
size_y = 40.0
margin = 30.0
[terrain]
resolution = 0.5
roughness = 0.0
"""


@pytest.fixture(scope="module")
def flat(tmp_path_factory: pytest.TempPathFactory) -> World:
    return World(load_scenario(_write(tmp_path_factory.mktemp("flat"))))


@cache
def world(name: str) -> World:
    return World(name)


def yaw_pitch_roll(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def test_ray_layout() -> None:
    lid = Lidar(world("valley"))
    assert lid.n_rays == 28_800 == len(lid.dirs)
    el = np.degrees(np.arcsin(lid.dirs[:16, 2]))
    assert np.allclose(el, np.arange(-15, 16, 2))
    az = np.degrees(np.arctan2(lid.dirs[::16, 1], lid.dirs[::16, 0])) % 360
    assert np.allclose(az, np.arange(1800) * 0.2)
    assert np.allclose(np.linalg.norm(lid.dirs, axis=1), 1)


@pytest.mark.parametrize("engine", ENGINES)
def test_flat_ground_exact_range_per_channel(flat: World, engine: str) -> None:
    height = 2.0
    lid = Lidar(flat, LidarConfig(noise_sigma=0.0, max_range=30.0, engine=engine))
    pts = lid.scan(np.array([1.3, -0.7, height]), np.eye(3), 0.0)
    assert pts.dtype == np.float32 and pts.shape[1] == 3
    el = np.radians(np.arange(-15, 16, 2))
    expect = {round(float(e), 6): height / math.sin(-e) for e in el
              if e < 0 and height / math.sin(-e) <= 30.0}
    assert len(expect) == 6  # -15 .. -5 degrees reach the ground within 30 m
    assert len(pts) == 1800 * len(expect)  # every such ray, nothing else
    r = np.linalg.norm(pts, axis=1)
    e = np.round(np.arcsin(pts[:, 2] / r), 6)
    for key, rng in expect.items():
        sel = np.isclose(e, key, atol=1e-5)
        assert sel.sum() == 1800
        assert np.allclose(r[sel], rng, atol=2e-4)
    assert np.allclose(pts[:, 2], -height, atol=2e-4)


@pytest.mark.parametrize("engine", ENGINES)
def test_min_and_max_range(flat: World, engine: str) -> None:
    cfg = LidarConfig(noise_sigma=0.0, max_range=10.0, min_range=5.0, engine=engine)
    lid = Lidar(flat, cfg)
    pts = lid.scan(np.array([0.0, 0.0, 2.0]), np.eye(3), 0.0)
    r = np.linalg.norm(pts, axis=1)
    assert len(pts) > 0 and r.min() >= 5.0 and r.max() <= 10.0
    # channels: 2 / sin(15, 13, 11 deg) = 7.7, 8.9, 10.5 m -> only 15 and 13 degrees
    assert len(pts) == 2 * 1800
    # a surface closer than min_range gives no return (and still occludes)
    near = Lidar(flat, LidarConfig(noise_sigma=0.0, min_range=2.5, engine=engine))
    assert len(near.scan(np.array([0.0, 0.0, 0.5]), np.eye(3), 0.0)) > 0
    assert np.linalg.norm(near.scan(np.array([0.0, 0.0, 0.5]), np.eye(3), 0.0), axis=1).min() \
        >= 2.5


def analytic_box_hits(origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray,
                      hi: np.ndarray) -> np.ndarray:
    """Slab test, independent of the package: distance per ray, inf on a miss."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origin) / dirs
        t2 = (hi - origin) / dirs
    tn = np.nanmax(np.minimum(t1, t2), axis=1)
    tf = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (tn <= tf) & (tn > 0)
    return np.where(hit, tn, np.inf)


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("yaw", [0.0, 0.7])
def test_box_hit_by_exactly_the_right_rays(tmp_path: Path, engine: str, yaw: float) -> None:
    w = World(load_scenario(_write(tmp_path)))
    lo, hi = np.array([3.1, -1.3, 1.7]), np.array([4.6, 2.2, 4.4])
    w.add_solids([box_solid((lo + hi) / 2, (hi - lo) / 2)])
    origin = np.array([0.2, 0.1, 3.5])
    rot = yaw_pitch_roll(yaw, 0.05, -0.03)
    lid = Lidar(w, LidarConfig(noise_sigma=0.0, max_range=10.0, engine=engine))
    dist = lid.ranges(origin, rot, 0.0)  # the ground is out of range (> 10 m away)
    expect = analytic_box_hits(origin, lid.dirs @ rot.T, lo, hi)
    got_hit, exp_hit = dist < 10.0, np.isfinite(expect)
    assert exp_hit.sum() > 500
    assert np.array_equal(got_hit, exp_hit)
    assert np.allclose(dist[got_hit], expect[exp_hit], atol=1e-4)
    # the points, taken to the world frame, lie on the box surface
    pts = lid.scan(origin, rot, 0.0) @ rot.T + origin
    assert len(pts) == exp_hit.sum()
    assert np.all((pts >= lo - 1e-3) & (pts <= hi + 1e-3))


def _write(tmp_path: Path) -> Path:
    p = tmp_path / "flat.toml"
    p.write_text(FLAT)
    return p


@pytest.mark.parametrize("engine", ENGINES)
def test_moving_aircraft_seen_where_it_is(engine: str) -> None:
    w = world("dynamic")
    lid = Lidar(w, LidarConfig(noise_sigma=0.0, max_range=4.5, engine=engine))
    for t in np.arange(0.0, 30.0, 0.5):  # a time when the spot beside it is open air
        box = w.aircraft_boxes(t)[0]
        centre, yaw = box[:3], math.atan2(box[7], box[6])
        # sensor 2.5 m to the aircraft's left (in its frame), same height
        side = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
        origin = centre + 2.5 * side
        if not w.collides_static(origin, 1.0):
            break
    pts = lid.scan(origin, np.eye(3), t) + origin

    def near_box(p: np.ndarray, b: np.ndarray) -> np.ndarray:
        c, s = b[6], b[7]
        d = p - b[:3]
        local = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])
        return np.all(np.abs(local) <= b[3:6] + 1e-3, axis=1)

    seen = near_box(pts, box)
    assert seen.sum() > 50
    assert np.allclose(np.abs((pts[seen] - centre) @ side), box[4], atol=1e-3)  # its side
    later = lid.scan(origin, np.eye(3), t + 8.0) + origin  # it has flown ~12 m on
    assert near_box(later, box).sum() == 0


@pytest.mark.parametrize("name", ["valley", "forest", "city"])
def test_engines_agree(name: str) -> None:
    w = world(name)
    rng = np.random.default_rng(11)
    starts = [w.sample_start_goal(rng)[0] for _ in range(6)]
    for max_range in (4.5, 100.0):
        a = Lidar(w, LidarConfig(max_range=max_range, engine="numba"))
        b = Lidar(w, LidarConfig(max_range=max_range, engine="embree"))
        for p in starts:
            rot = yaw_pitch_roll(rng.uniform(-3, 3), rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2))
            da, db = a.ranges(p, rot, 0.0).copy(), b.ranges(p, rot, 0.0)
            ha, hb = da < max_range, db < max_range
            assert (ha != hb).sum() <= 2  # grazing rays along a shared edge may differ
            both = ha & hb
            assert np.allclose(da[both], db[both], atol=2e-3)


def test_auto_engine_and_truncated_scan_matches_full() -> None:
    w = world("valley")
    assert Lidar(w, LidarConfig(max_range=4.5)).engine == "numba"
    assert Lidar(w, LidarConfig()).engine == "embree"
    p = w.sample_start_goal(np.random.default_rng(1))[0]
    rot = yaw_pitch_roll(0.3)
    full = Lidar(w, LidarConfig(noise_sigma=0.0)).ranges(p, rot, 0.0).copy()
    short = Lidar(w, LidarConfig(noise_sigma=0.0, max_range=4.5)).ranges(p, rot, 0.0)
    assert (short < 4.5).sum() > 0
    assert ((short < 4.5) != (full < 4.5)).sum() <= 2


@pytest.mark.parametrize("name", ["valley", "forest"])
def test_truncated_culling_loses_no_hit(name: str) -> None:
    """Short-range scans (culled) against full-range Embree scans (not culled)."""
    w = world(name)
    rng = np.random.default_rng(3)
    short = Lidar(w, LidarConfig(max_range=4.5))
    full = Lidar(w, LidarConfig(max_range=100.0, engine="embree"))
    checked = 0
    while checked < 25:
        s, g = w.sample_start_goal(rng)
        d = (g - s) / np.linalg.norm(g - s)
        for k in range(0, int(np.linalg.norm(g - s)), 2):  # towards the goal, into hills
            p = s + d * k + np.array([0.0, 0.0, rng.uniform(-2.0, 2.0)])
            if w.collides_static(p, 0.3):
                break
            tilt = rng.uniform(-0.5, 0.5, size=2)
            rot = yaw_pitch_roll(rng.uniform(-3, 3), *tilt)
            a = short.ranges(p, rot, 0.0) < 4.5
            b = full.ranges(p, rot, 0.0) < 4.5
            assert (a != b).sum() <= 2, (p, (a != b).sum())
            checked += 1


def test_seeded_noise() -> None:
    w = world("valley")
    p, rot = w.sample_start_goal(np.random.default_rng(4))[0], yaw_pitch_roll(1.0)
    a = Lidar(w, LidarConfig(), seed=5).scan(p, rot, 0.0)
    b = Lidar(w, LidarConfig(), seed=5).scan(p, rot, 0.0)
    c = Lidar(w, LidarConfig(), seed=6).scan(p, rot, 0.0)
    assert np.array_equal(a, b) and len(a) > 1000
    assert not np.array_equal(a, c)
    clean = Lidar(w, LidarConfig(noise_sigma=0.0)).scan(p, rot, 0.0)
    err = np.linalg.norm(a, axis=1) - np.linalg.norm(clean, axis=1)
    assert 0.02 < err.std() < 0.04 and abs(err.mean()) < 0.005
    lid = Lidar(w, LidarConfig(), seed=9)
    first = lid.scan(p, rot, 0.0)
    lid.reseed(9)
    assert np.array_equal(first, lid.scan(p, rot, 0.0))


@pytest.mark.parametrize("name", ["valley", "city"])
def test_rings_from_the_rays_are_the_elevation_rings(name: str) -> None:
    """``scan_rings`` hands over each return's channel; it is what the sim publishes as
    the cloud's ``ring`` and must equal ``bus.messages.elevation_rings`` of the point."""
    from bus.messages import elevation_rings

    w = world(name)
    rng = np.random.default_rng(7)
    cfg = LidarConfig(max_range=4.5)
    a, b = Lidar(w, cfg, seed=3), Lidar(w, cfg, seed=3)
    returns = 0
    for _ in range(8):
        p = w.sample_start_goal(rng)[0] + np.array([0.0, 0.0, rng.uniform(-1.5, 0.5)])
        rot = yaw_pitch_roll(rng.uniform(-3, 3), *rng.uniform(-0.3, 0.3, size=2))
        points, rings = a.scan_rings(p, rot, 0.0)
        assert np.array_equal(points, b.scan(p, rot, 0.0))  # same points, same noise
        assert rings.dtype == np.uint16 and rings.shape == (len(points),)
        assert np.array_equal(rings, elevation_rings(points, cfg.min_elevation_deg,
                                                     cfg.max_elevation_deg, cfg.channels))
        returns += len(points)
    assert returns > 1000


def test_nothing_in_range_gives_empty_scan() -> None:
    lid = Lidar(world("valley"), LidarConfig(max_range=4.5))
    pts = lid.scan(np.array([0.0, 0.0, 60.0]), np.eye(3), 0.0)
    assert pts.shape == (0, 3) and pts.dtype == np.float32


def test_config_validation() -> None:
    with pytest.raises(ValueError):
        LidarConfig(min_range=5.0, max_range=4.0)
    with pytest.raises(ValueError):
        LidarConfig(engine="optix")
