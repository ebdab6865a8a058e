"""ENU/FLU <-> NED/FRD conversions: known cases, round trips, agreement with rotation matrices."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mavlink_bridge import frames

RNG = np.random.default_rng(7)
# ENU -> NED coordinates; FRD -> FLU coordinates (both proper rotations by pi).
T_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
F_FLU_FRD = np.diag([1.0, -1.0, -1.0])


def rot_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def rot_quat(q: tuple[float, float, float, float]) -> np.ndarray:
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def random_euler() -> tuple[float, float, float]:
    return (float(RNG.uniform(-math.pi, math.pi)), float(RNG.uniform(-1.5, 1.5)),
            float(RNG.uniform(-math.pi, math.pi)))


def test_world_vectors_known_and_round_trip() -> None:
    assert frames.enu_to_ned(1.0, 2.0, 3.0) == (2.0, 1.0, -3.0)  # east 1, north 2, up 3
    assert frames.ned_to_enu(2.0, 1.0, -3.0) == (1.0, 2.0, 3.0)
    for v in RNG.normal(size=(50, 3)):
        assert frames.ned_to_enu(*frames.enu_to_ned(*v)) == tuple(v)
        assert np.allclose(frames.enu_to_ned(*v), T_NED_ENU @ v)


def test_body_vectors_known_and_round_trip() -> None:
    assert frames.flu_to_frd(1.0, 2.0, 3.0) == (1.0, -2.0, -3.0)  # left 2 = right -2
    for v in RNG.normal(size=(50, 3)):
        assert frames.frd_to_flu(*frames.flu_to_frd(*v)) == tuple(v)


@pytest.mark.parametrize(("enu", "ned"), [
    (0.0, math.pi / 2),  # facing east
    (math.pi / 2, 0.0),  # facing north
    (math.pi, -math.pi / 2),  # west
    (-math.pi / 2, -math.pi),  # south (wrapped to [-pi, pi))
])
def test_yaw_known(enu: float, ned: float) -> None:
    assert frames.yaw_enu_to_ned(enu) == pytest.approx(ned, abs=1e-12)
    assert math.cos(frames.yaw_ned_to_enu(ned) - enu) == pytest.approx(1.0)


def test_yaw_round_trip_and_rate() -> None:
    for yaw in RNG.uniform(-math.pi, math.pi, 100):
        back = frames.yaw_ned_to_enu(frames.yaw_enu_to_ned(float(yaw)))
        assert back == pytest.approx(yaw, abs=1e-12)
        assert -math.pi <= frames.yaw_enu_to_ned(float(yaw)) < math.pi
    assert frames.yaw_rate_enu_to_ned(0.5) == -0.5  # CCW from above = CW-negative
    assert frames.yaw_rate_ned_to_enu(frames.yaw_rate_enu_to_ned(0.3)) == 0.3


def test_quaternion_matches_matrices_and_euler() -> None:
    assert frames.quat_enu_to_ned((1.0, 0.0, 0.0, 0.0)) == pytest.approx(
        (math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)))  # level, facing east: NED yaw +90 deg
    for _ in range(100):
        roll, pitch, yaw = random_euler()
        r_enu = rot_zyx(roll, pitch, yaw)
        q_enu = frames.quat_from_euler(roll, pitch, yaw)
        assert np.allclose(rot_quat(q_enu), r_enu)
        q_ned = frames.quat_enu_to_ned(q_enu)
        r_ned = T_NED_ENU @ r_enu @ F_FLU_FRD  # FRD -> FLU -> ENU -> NED
        assert np.allclose(rot_quat(q_ned), r_ned)
        # Euler conversion agrees with the quaternion one.
        e_ned = frames.euler_enu_to_ned(roll, pitch, yaw)
        assert np.allclose(rot_zyx(*e_ned), r_ned)
        assert np.allclose(frames.euler_from_quat(q_ned)[:2], e_ned[:2])
        assert math.cos(frames.euler_from_quat(q_ned)[2] - e_ned[2]) == pytest.approx(1.0)
        # Round trips.
        assert np.allclose(frames.quat_ned_to_enu(q_ned), q_enu)
        back = frames.euler_ned_to_enu(*e_ned)
        assert np.allclose(back[:2], (roll, pitch))
        assert math.cos(back[2] - yaw) == pytest.approx(1.0)


def test_body_rates_follow_the_frame_change() -> None:
    for w in RNG.normal(size=(20, 3)):
        assert np.allclose(frames.body_rates_flu_to_frd(*w), F_FLU_FRD @ w)
        assert frames.body_rates_frd_to_flu(*frames.body_rates_flu_to_frd(*w)) == tuple(w)


def test_velocity_setpoints_round_trip() -> None:
    # North-east-down 1, 2, -0.5 with CW 0.3 rad/s = east 2, north 1, up 0.5, CCW -0.3.
    assert frames.velocity_local_ned_to_enu(1.0, 2.0, -0.5, 0.3) == (2.0, 1.0, 0.5, -0.3)
    assert frames.velocity_body_ned_to_flu(1.0, 2.0, -0.5, 0.3) == (1.0, -2.0, 0.5, -0.3)
    for v in RNG.normal(size=(50, 4)):
        t = tuple(float(x) for x in v)
        assert frames.velocity_local_ned_to_enu(*frames.velocity_enu_to_local_ned(*t)) == t
        assert frames.velocity_body_ned_to_flu(*frames.velocity_flu_to_body_ned(*t)) == t
