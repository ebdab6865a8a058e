"""Face values (eq. 3.1, 3.2), goal angles, observation and frame stacking."""

from __future__ import annotations

import math

import numpy as np
import pytest

from perception.faces import face_values, reduce_points
from perception.icosahedron import TruncatedIcosahedron
from perception.observation import (
    FrameStacker,
    ObservationConfig,
    build_observation,
    goal_angles,
)

BACKENDS = ["numba", "numpy"]


@pytest.fixture(scope="module")
def ico() -> TruncatedIcosahedron:
    return TruncatedIcosahedron(4.0)


def reference_face_values(points, ico, encoding="distance"):
    """Slow, literal eq. 3.1 / 3.2: a Python loop over the points."""
    best = [math.inf] * 32
    for p in np.asarray(points, dtype=np.float64):
        if not np.all(np.isfinite(p)):
            continue
        if any(float(ico.normals[i] @ p) > ico.offsets[i] for i in range(32)):
            continue  # eq. 3.1: outside at least one face plane
        dists = [float(np.linalg.norm(p - ico.centres[i])) for i in range(32)]
        k = int(np.argmin(dists))  # eq. 3.2: nearest face centre
        val = dists[k] if encoding == "distance" else float(np.linalg.norm(p))
        best[k] = min(best[k], val)
    out = np.zeros(32)
    for k, b in enumerate(best):
        if b < math.inf:
            out[k] = b if encoding == "distance" else 1.0 - b / ico.radius
    return out


# ---------------------------------------------------------------- face values


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("t", [1.0, 2.0, 3.0, 3.5])
def test_point_behind_face_k(ico, backend, t):
    for k in range(32):
        p = (t * ico.normals[k])[None, :].astype(np.float32)
        res = reduce_points(p, ico, backend=backend)
        assert res.values.dtype == np.float32 and res.values.shape == (32,)
        assert res.n_inside == 1
        nz = np.flatnonzero(res.values)
        assert nz.tolist() == [k]
        expected = np.linalg.norm(p[0].astype(np.float64) - ico.centres[k])
        assert res.values[k] == pytest.approx(expected, rel=1e-6)
        assert res.values[k] == pytest.approx(ico.offsets[k] - t, abs=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_minimum_over_points_of_a_face(ico, backend):
    n = ico.normals[5]
    pts = np.array([2.0 * n, 3.0 * n, 2.5 * n], dtype=np.float32)
    vals = reduce_points(pts, ico, backend=backend).values
    assert vals[5] == pytest.approx(ico.offsets[5] - 3.0, abs=1e-6)  # the nearest to c_5
    assert np.count_nonzero(vals) == 1


@pytest.mark.parametrize("backend", BACKENDS)
def test_points_outside_ignored(ico, backend):
    pts = []
    for k in range(32):
        pts.append((ico.offsets[k] + 0.02) * ico.normals[k])  # inside the sphere, beyond face
        pts.append(10.0 * ico.normals[k])
    pts = np.array(pts, dtype=np.float32)
    assert np.all(np.linalg.norm(pts[::2], axis=1) < ico.radius)
    res = reduce_points(pts, ico, backend=backend)
    assert res.n_inside == 0
    np.testing.assert_array_equal(res.values, np.zeros(32, np.float32))


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty(ico, backend):
    for pts in (np.zeros((0, 3), np.float32), np.zeros((0, 3)), np.zeros(0), []):
        res = reduce_points(pts, ico, backend=backend)
        np.testing.assert_array_equal(res.values, np.zeros(32, np.float32))
        assert res.values.dtype == np.float32
        assert (res.n_inside, res.n_invalid) == (0, 0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_nan_and_inf_ignored_and_counted(ico, backend):
    good = 2.0 * ico.normals[7]
    pts = np.array(
        [[np.nan, 0, 0], good, [0, np.inf, 0], [np.nan] * 3, [-np.inf, 1, 1]], np.float32
    )
    res = reduce_points(pts, ico, backend=backend)
    assert res.n_invalid == 4
    assert res.n_inside == 1
    assert np.flatnonzero(res.values).tolist() == [7]


@pytest.mark.parametrize("backend", BACKENDS)
def test_float64_and_non_contiguous_input(ico, backend):
    rng = np.random.default_rng(1)
    pts64 = rng.uniform(-4.5, 4.5, size=(500, 3))
    pts32 = pts64.astype(np.float32)
    a = reduce_points(pts32, ico, backend=backend).values
    b = reduce_points(pts32.astype(np.float64), ico, backend=backend).values
    np.testing.assert_array_equal(a, b)
    wide = np.zeros((500, 6), np.float32)
    wide[:, ::2] = pts32
    np.testing.assert_array_equal(reduce_points(wide[:, ::2], ico, backend=backend).values, a)
    ints = np.array([[1, 0, 0], [0, 2, 0]])
    assert np.count_nonzero(face_values(ints, ico)) == 2


def test_bad_arguments(ico):
    with pytest.raises(ValueError):
        face_values(np.zeros((4, 2)), ico)
    with pytest.raises(ValueError):
        face_values(np.zeros((4, 3)), ico, encoding="nope")
    with pytest.raises(ValueError):
        reduce_points(np.zeros((4, 3)), ico, backend="nope")


@pytest.mark.parametrize("backend", BACKENDS)
def test_proximity_encoding(ico, backend):
    n3, n20 = ico.normals[3], ico.normals[20]
    pts = np.array([1.0 * n3, 3.0 * n3, 2.0 * n20], dtype=np.float32)
    vals = reduce_points(pts, ico, encoding="proximity", backend=backend).values
    assert vals[3] == pytest.approx(1.0 - 1.0 / 4.0, abs=1e-6)  # the closer point wins
    assert vals[20] == pytest.approx(1.0 - 2.0 / 4.0, abs=1e-6)
    assert np.count_nonzero(vals) == 2
    free = face_values(np.array([[50.0, 0, 0]], np.float32), ico, encoding="proximity")
    np.testing.assert_array_equal(free, np.zeros(32, np.float32))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("encoding", ["distance", "proximity"])
def test_matches_slow_reference(ico, backend, encoding):
    rng = np.random.default_rng(12345)
    for trial in range(5):
        n = int(rng.integers(1, 400))
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        r = rng.uniform(0.0, 4.6, size=n)  # inside, between in- and circumsphere, beyond
        pts = (d * r[:, None]).astype(np.float32)
        pts[rng.random(n) < 0.02] = np.nan
        got = reduce_points(pts, ico, encoding=encoding, backend=backend)
        want = reference_face_values(pts, ico, encoding)
        np.testing.assert_allclose(got.values, want, rtol=1e-6, atol=1e-6, err_msg=str(trial))
        inside = ico.contains(np.nan_to_num(pts, nan=1e9)).sum()
        assert got.n_inside == inside
        assert got.n_invalid == int(np.isnan(pts).any(axis=1).sum())


def test_nearest_centre_not_cone(ico):
    # eq. 3.2's rule: a point close to the UAV along a pentagon normal is nearer to a
    # hexagon centre (the hexagon planes are closer), so it belongs to that hexagon.
    p = (0.2 * ico.normals[0])[None, :]
    vals = face_values(p, ico)
    k = int(np.flatnonzero(vals)[0])
    assert not ico.is_pentagon[k]
    assert vals[k] == pytest.approx(np.linalg.norm(p[0] - ico.centres[k]), rel=1e-6)


def test_backends_agree_on_a_big_cloud(ico):
    rng = np.random.default_rng(7)
    pts = rng.uniform(-6, 6, size=(30_000, 3)).astype(np.float32)
    for enc in ("distance", "proximity"):
        a = reduce_points(pts, ico, enc, backend="numba")
        b = reduce_points(pts, ico, enc, backend="numpy")
        np.testing.assert_allclose(a.values, b.values, rtol=1e-6)
        assert a.n_inside == b.n_inside > 0


# ---------------------------------------------------------------- goal angles

ORIGIN = np.array([0.0, 0.0, 3.5])
STILL = np.zeros(3)


@pytest.mark.parametrize(
    "goal, yaw, h",
    [
        ((10, 0), 0.0, 0.0),  # straight ahead
        ((0, 10), 0.0, 90.0),  # to the left
        ((-10, 0), 0.0, 180.0),  # behind
        ((0, -10), 0.0, 270.0),  # to the right
        ((10, 10), 0.0, 45.0),
        ((0, 10), math.pi / 2, 0.0),  # facing north, goal north
        ((10, 0), math.pi / 2, 270.0),  # facing north, goal east: to the right
        ((-10, 0), -math.pi / 2, 270.0),  # facing south, goal west: to the right
        ((10, 0), 2 * math.pi, 0.0),
    ],
)
def test_goal_angle_h(goal, yaw, h):
    g3 = np.array([goal[0], goal[1], 8.0])
    got_h, got_g = goal_angles(ORIGIN, yaw, STILL, g3)
    assert got_h == pytest.approx(h, abs=1e-9)
    assert got_g == got_h  # hovering: g falls back to the heading
    assert 0.0 <= got_h < 360.0


def test_goal_angle_g_uses_horizontal_velocity():
    goal = np.array([0.0, 10.0, 3.5])
    h, g = goal_angles(ORIGIN, 0.0, np.array([1.0, 0.0, 5.0]), goal)  # flying east
    assert h == pytest.approx(90.0)
    assert g == pytest.approx(90.0)
    h, g = goal_angles(ORIGIN, 0.0, np.array([0.0, -1.5, 0.0]), goal)  # flying south
    assert h == pytest.approx(90.0)
    assert g == pytest.approx(180.0)
    h, g = goal_angles(ORIGIN, 0.0, np.array([-1.0, 1.0, 0.0]), goal)  # flying north-west
    assert g == pytest.approx(315.0)  # goal is 45 deg clockwise of the velocity
    _, g = goal_angles(ORIGIN, 0.0, np.array([0.05, -0.05, 2.0]), goal)  # below min speed
    assert g == pytest.approx(90.0)


def test_goal_angles_edge_cases():
    # goal exactly above: direction undefined -> 0
    assert goal_angles(ORIGIN, 1.0, STILL, np.array([0.0, 0.0, 9.0])) == (0.0, 0.0)
    # a bearing a hair clockwise of the heading wraps into [0, 360), never to 360.0
    yaw = math.atan2(1.0, 10.0) + 1e-17
    h, _ = goal_angles(ORIGIN, yaw, STILL, np.array([10.0, 1.0, 0.0]))
    assert 0.0 <= h < 360.0
    rng = np.random.default_rng(3)
    for _ in range(200):
        pos, goal = rng.uniform(-50, 50, 3), rng.uniform(-50, 50, 3)
        h, g = goal_angles(pos, rng.uniform(-10, 10), rng.normal(size=3), goal)
        assert 0.0 <= h < 360.0 and 0.0 <= g < 360.0


# ---------------------------------------------------------------- observation


def test_build_observation_scaling():
    f = np.linspace(0.0, 3.1, 32)
    obs = build_observation(f, 3.5, 90.0, 270.0, ObservationConfig())
    assert obs.shape == (35,) and obs.dtype == np.float32
    np.testing.assert_allclose(obs[:32], f / 4.0, rtol=1e-6)
    assert obs[32] == pytest.approx(0.35)
    assert obs[33] == pytest.approx(0.5)
    assert obs[34] == pytest.approx(1.5)


def test_build_observation_options():
    f = np.full(32, 0.25)
    prox = build_observation(f, 0.0, 0.0, 0.0, ObservationConfig(encoding="proximity"))
    np.testing.assert_allclose(prox[:32], 0.25)  # proximity is already in [0, 1]
    cfg = ObservationConfig(centre_angles=True)
    obs = build_observation(f, 0.0, 350.0, 180.0, cfg)
    assert obs[33] == pytest.approx(-10.0 / 180.0)
    assert obs[34] == pytest.approx(-1.0)
    obs = build_observation(f, 0.0, 10.0, 179.0, cfg)
    assert obs[33] == pytest.approx(10.0 / 180.0)
    assert obs[34] == pytest.approx(179.0 / 180.0)
    assert build_observation(f, 1.0, 0.0, 0.0)[32] == pytest.approx(0.1)  # default config


def test_build_observation_rejects_bad_input():
    with pytest.raises(ValueError):
        build_observation(np.zeros(31), 1.0, 0.0, 0.0, ObservationConfig())
    with pytest.raises(ValueError):
        build_observation(np.zeros(32), float("nan"), 0.0, 0.0, ObservationConfig())
    f = np.zeros(32)
    f[3] = np.inf
    with pytest.raises(ValueError):
        build_observation(f, 1.0, 0.0, 0.0, ObservationConfig())
    with pytest.raises(ValueError):
        ObservationConfig(encoding="nope")
    with pytest.raises(ValueError):
        ObservationConfig(radius=0.0)


def test_pipeline_point_to_observation(ico):
    p = (3.0 * ico.normals[12])[None, :].astype(np.float32)
    obs = build_observation(face_values(p, ico), 3.5, 0.0, 0.0, ObservationConfig())
    assert obs[12] == pytest.approx((ico.offsets[12] - 3.0) / 4.0, rel=1e-5)
    assert np.count_nonzero(obs[:32]) == 1


# ---------------------------------------------------------------- frame stacker


def test_frame_stacker_fifo_and_padding():
    st = FrameStacker(frames=3, dim=35)
    o = [np.full(35, float(i + 1), np.float32) for i in range(5)]
    s1 = st.push(o[0])
    assert s1.shape == (3, 35) and s1.dtype == np.float32
    np.testing.assert_array_equal(s1, np.stack([np.zeros(35), np.zeros(35), o[0]]))
    s2 = st.push(o[1])
    np.testing.assert_array_equal(s2, np.stack([np.zeros(35), o[0], o[1]]))
    s3 = st.push(o[2])
    np.testing.assert_array_equal(s3, np.stack(o[:3]))  # oldest first, newest last
    s4 = st.push(o[3])
    np.testing.assert_array_equal(s4, np.stack(o[1:4]))
    # returned stacks are copies, not views of the internal buffer
    np.testing.assert_array_equal(s1, np.stack([np.zeros(35), np.zeros(35), o[0]]))
    s4[:] = -1
    np.testing.assert_array_equal(st.state, np.stack(o[1:4]))
    assert st.count == 4


def test_frame_stacker_reset_between_episodes():
    st = FrameStacker()
    for i in range(4):
        st.push(np.full(35, i + 1.0))
    st.reset()
    np.testing.assert_array_equal(st.state, np.zeros((3, 35), np.float32))
    assert st.count == 0
    new = np.arange(35, dtype=np.float32)
    s = st.push(new)
    np.testing.assert_array_equal(s[:2], 0.0)  # nothing from the previous episode
    np.testing.assert_array_equal(s[2], new)


def test_frame_stacker_shapes():
    st = FrameStacker(frames=1, dim=4)
    np.testing.assert_array_equal(st.push(np.ones(4)), np.ones((1, 4)))
    with pytest.raises(ValueError):
        st.push(np.ones(5))
    with pytest.raises(ValueError):
        FrameStacker(frames=0)
