"""Velocity autopilot: setpoint validation, anti-windup, hover hold and step responses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl.flight.autopilot import VelocityAutopilot
from sitl.flight.vehicle import Vehicle

START = np.array([0.0, 0.0, 3.5])


@pytest.fixture(scope="module")
def vehicle() -> Vehicle:
    return Vehicle(seed=0)


# ------------------------------------------------------------------ unit: setpoints
def test_setpoints_saturated_to_limits() -> None:
    ap = VelocityAutopilot(max_speed_xy=2.0, max_speed_z=2.0, max_yaw_rate=2.0)
    assert ap.set_setpoint(5.0, -3.0, 9.0, -7.0)
    assert ap.setpoint == (2.0, -2.0, 2.0, -2.0)
    assert ap.set_setpoint(1.0, -0.5, 0.25, 0.5)
    assert ap.setpoint == (1.0, -0.5, 0.25, 0.5)
    ap = VelocityAutopilot(max_speed_xy=1.0, max_speed_z=0.5, max_yaw_rate=0.3)
    ap.set_setpoint(-4.0, 4.0, -4.0, 4.0)
    assert ap.setpoint == (-1.0, 1.0, -0.5, 0.3)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "x", None])
def test_non_finite_setpoints_rejected_last_valid_holds(bad: object) -> None:
    ap = VelocityAutopilot()
    ap.set_setpoint(1.0, 0.5, -0.5, 0.2)
    assert not ap.set_setpoint(0.0, bad, 0.0, 0.0)  # type: ignore[arg-type]
    assert not ap.set_setpoint(0.0, 0.0, 0.0, bad)  # type: ignore[arg-type]
    assert ap.rejected == 2
    assert ap.setpoint == (1.0, 0.5, -0.5, 0.2)


def test_rejections_logged_without_flooding(caplog: pytest.LogCaptureFixture) -> None:
    ap = VelocityAutopilot()
    with caplog.at_level("WARNING", logger="sitl.flight.autopilot"):
        for _ in range(100):
            ap.set_setpoint(math.nan, 0.0, 0.0, 0.0)
    assert ap.rejected == 100
    assert 1 <= len(caplog.records) <= 8  # 1st, 2nd, 4th, ..., 64th
    assert "rejected" in caplog.records[0].getMessage()


def test_integrators_do_not_wind_up_while_saturated() -> None:
    ap = VelocityAutopilot()
    ap.set_setpoint(2.0, 0.0, 2.0, 0.0)
    for _ in range(500):  # 10 s with the vehicle stuck: errors stay large
        ap.update((0.0, 0.0, 0.0), (-3.0, 0.0, -3.0), 0.02)
    assert ap._ix == 0.0 and ap._iz == 0.0  # outputs saturated: no integration
    ap.set_setpoint(0.1, 0.0, 0.1, 0.0)
    for _ in range(5000):  # small, unsaturated errors: integrals bounded by the clamps
        ap.update((0.0, 0.0, 0.0), (-0.5, 0.0, -0.5), 0.02)
    assert 0.0 < ap._ix <= ap.config.max_int_xy
    assert 0.0 < ap._iz <= ap.config.max_int_z


# ------------------------------------------------------------------ closed loop
def _fly(v: Vehicle, setpoint: list[float], seconds: float) -> np.ndarray:
    rows = []
    for _ in range(round(seconds / v.config.control_period)):
        v.step(np.asarray(setpoint, dtype=float))
        t = v.truth
        rows.append(np.r_[t.time, t.position, t.velocity, t.rpy[2]])
    return np.array(rows)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hover_holds_position(vehicle: Vehicle, seed: int) -> None:
    vehicle.reset(START, 0.4, seed=seed)
    tr = _fly(vehicle, [0.0, 0.0, 0.0, 0.0], 30.0)
    assert np.abs(tr[:, 3] - 3.5).max() < 0.2
    assert np.hypot(tr[:, 1], tr[:, 2]).max() < 0.3


def _step(v: Vehicle, axis: int, target: float, seed: int) -> tuple[float, float]:
    """Time to 90 % and overshoot (fraction) of a step from hover on one setpoint axis."""
    v.reset(START + [0.0, 0.0, 2.0], 0.0, seed=seed)
    _fly(v, [0.0, 0.0, 0.0, 0.0], 1.0)
    yaw_before = v.truth.rpy[2]
    sp = [0.0, 0.0, 0.0, 0.0]
    sp[axis] = target
    tr = _fly(v, sp, 4.0)
    if axis < 3:
        val = tr[:, 4 + axis]
    else:  # world yaw rate, averaged over each control period
        val = np.diff(np.unwrap(np.r_[yaw_before, tr[:, 7]])) / v.config.control_period
    ratio = val / target
    reached = np.nonzero(ratio >= 0.9)[0]
    t90 = (reached[0] + 1) * v.config.control_period if reached.size else math.inf
    return t90, float(ratio.max() - 1.0)


@pytest.mark.parametrize(
    ("axis", "target"),
    [(0, 2.0), (1, 2.0), (0, -2.0), (2, 1.0), (2, -1.0), (3, 1.0), (3, -2.0)],
    ids=["vx", "vy", "-vx", "vz", "-vz", "yaw_rate", "-yaw_rate_max"],
)
def test_step_response(vehicle: Vehicle, axis: int, target: float) -> None:
    for seed in (3, 4):
        t90, overshoot = _step(vehicle, axis, target, seed)
        assert t90 <= 2.0, (t90, overshoot)
        assert overshoot < 0.2, (t90, overshoot)


def test_out_of_range_setpoint_flies_at_the_limit(vehicle: Vehicle) -> None:
    vehicle.reset(START + [0.0, 0.0, 5.0], 0.0, seed=5)
    tr = _fly(vehicle, [6.0, 0.0, 0.0, 0.0], 6.0)
    assert vehicle.autopilot.setpoint[0] == 2.0
    assert tr[-10:, 4].mean() == pytest.approx(2.0, abs=0.1)
    assert tr[:, 4].max() < 2.4


def test_vehicle_rejects_nan_and_keeps_flying_last_setpoint(vehicle: Vehicle) -> None:
    vehicle.reset(START, 0.0, seed=6)
    _fly(vehicle, [1.0, 0.0, 0.0, 0.0], 3.0)
    assert vehicle.rejected_setpoints == 0
    _fly(vehicle, [math.nan, 0.0, 0.0, 0.0], 1.0)
    vehicle.step(np.array([0.0, math.inf, 0.0, 0.0]))
    vehicle.step(np.array([0.0, 0.0, -math.inf, math.nan]))
    assert vehicle.rejected_setpoints == 12
    assert vehicle.autopilot.setpoint == (1.0, 0.0, 0.0, 0.0)
    assert vehicle.truth.velocity[0] == pytest.approx(1.0, abs=0.15)
    vehicle.reset(START, 0.0)
    assert vehicle.rejected_setpoints == 0
    with pytest.raises(ValueError):
        vehicle.step(np.zeros(3))


def test_world_velocity_tracked_while_yawing(vehicle: Vehicle) -> None:
    """The tilt direction follows the heading: east stays east while spinning at 2 rad/s."""
    vehicle.reset(START + [0.0, 0.0, 2.0], 0.0, seed=7)
    tr = _fly(vehicle, [1.5, -1.0, 0.0, 2.0], 8.0)
    late = tr[30:]
    assert np.abs(late[:, 4] - 1.5).max() < 0.25
    assert np.abs(late[:, 5] + 1.0).max() < 0.25
    assert np.abs(late[:, 6]).max() < 0.25
