"""JSBSim F450 flight model: silent loading, placement, force balance, inner loops, resets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl.flight.flight_model import FlightModel, enu_rpy, rotation_flu_to_enu


@pytest.fixture(scope="module")
def fm() -> FlightModel:
    return FlightModel()


def _rot_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch),
                              math.sin(pitch), math.cos(yaw), math.sin(yaw))
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def test_loading_prints_nothing(capfd: pytest.CaptureFixture[str]) -> None:
    FlightModel()
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_reset_places_vehicle_hovering_at_enu_pose(fm: FlightModel) -> None:
    fm.reset(12.5, -7.25, 3.5, 1.2)
    assert np.allclose(fm.position(), (12.5, -7.25, 3.5), atol=1e-6)
    assert np.allclose(fm.velocity(), 0.0, atol=1e-9)
    roll, pitch, yaw = enu_rpy(*fm.euler_ned())
    assert abs(roll) < 1e-9 and abs(pitch) < 1e-9 and yaw == pytest.approx(1.2, abs=1e-9)
    # propellers are already at hover speed: the vehicle barely moves in 1 s, open loop
    fm.run(500)
    e, n, u = fm.position()
    assert abs(u - 3.5) < 0.05 and math.hypot(e - 12.5, n + 7.25) < 0.05


def test_enu_conventions_match_rotation_matrix() -> None:
    for phi, theta, psi in [(0.1, 0.2, 0.3), (-0.4, 0.25, 2.9), (0.0, -0.3, -1.0)]:
        r = np.array(rotation_flu_to_enu(phi, theta, psi))
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.allclose(r, _rot_zyx(*enu_rpy(phi, theta, psi)), atol=1e-12)
    # heading north (psi = 0) is ENU yaw pi/2: the body x axis points north
    r = np.array(rotation_flu_to_enu(0.0, 0.0, 0.0))
    assert np.allclose(r[:, 0], (0.0, 1.0, 0.0))


def test_hover_throttle_balances_gravity(fm: FlightModel) -> None:
    fm.reset(0.0, 0.0, 3.5, 0.0)
    fm.run(1)
    f_up = fm.specific_force_flu()[2]
    assert f_up == pytest.approx(fm.gravity, rel=0.005)
    assert 0.4 < fm.hover_throttle < 0.42


def test_tilt_gives_rigid_body_acceleration(fm: FlightModel) -> None:
    """Force balance: with altitude held, a steady tilt theta accelerates at ~g tan(theta)."""
    fm.reset(0.0, 0.0, 20.0, 0.5 * math.pi)  # facing north
    tilt = math.tan(math.radians(10.0))
    i_vz = 0.0
    v_start = 0.0
    for k in range(100):  # 2 s, 50 Hz vertical PI on truth
        vz = fm.velocity()[2]
        i_vz += -vz * 0.02
        thr = fm.hover_throttle * math.sqrt(math.hypot(1.0, tilt)) - 0.15 * vz + 0.1 * i_vz
        fm.set_commands(0.0, tilt, thr, 0.0)
        fm.run(10)
        if k == 49:
            v_start = fm.velocity()[1]
    a_north = (fm.velocity()[1] - v_start) / 1.0
    assert a_north == pytest.approx(fm.gravity * tilt, rel=0.08)
    _, pitch, _ = enu_rpy(*fm.euler_ned())
    assert pitch == pytest.approx(math.radians(10.0), abs=0.01)  # nose down toward north


def test_yaw_rate_beyond_stock_fcs_cap(fm: FlightModel) -> None:
    """The stock FlightControl.xml caps rate references at 0.75 rad/s; ours reaches 2."""
    fm.reset(0.0, 0.0, 10.0, 0.0)
    fm.set_commands(0.0, 0.0, fm.hover_throttle, 2.0)
    fm.run(500)
    y0 = enu_rpy(*fm.euler_ned())[2]
    fm.run(50)
    y1 = enu_rpy(*fm.euler_ned())[2]
    rate = math.remainder(y1 - y0, 2 * math.pi) / 0.1
    assert rate == pytest.approx(2.0, abs=0.15)


def test_reset_is_bit_identical_after_other_flights(fm: FlightModel) -> None:
    def fly() -> list[tuple[float, ...]]:
        fm.reset(3.0, 4.0, 6.0, 0.5)
        out = []
        for k in range(40):
            fm.set_commands(0.1 * math.sin(k), 0.1 * math.cos(k), 0.42, 0.5)
            fm.run(10)
            out.append(fm.position() + fm.velocity() + fm.euler_ned())
        return out

    first = fly()
    fm.reset(-50.0, 80.0, 2.0, -2.0)
    fm.set_commands(0.3, -0.2, 0.5, -1.0)
    fm.run(700)
    assert fly() == first
