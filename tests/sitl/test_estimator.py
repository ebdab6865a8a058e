"""Sensors and estimator: seeded noise, estimate accuracy in flight, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sitl.flight.estimator import Estimator
from sitl.flight.sensors import Sensors
from sitl.flight.vehicle import Vehicle


@pytest.fixture(scope="module")
def vehicle() -> Vehicle:
    return Vehicle(seed=0)


def _random_flight(v: Vehicle, seed: int, seconds: float = 60.0) -> dict[str, np.ndarray]:
    """Random setpoints held 2 s each (all four axes), kept between 6 and 14 m altitude."""
    v.reset(np.array([5.0, -3.0, 10.0]), 0.7, seed=seed)
    rng = np.random.default_rng(1000 + seed)
    rows: dict[str, list] = {k: [] for k in ("tp", "tv", "ty", "ep", "ev", "ey")}
    sp = np.zeros(4)
    for k in range(round(seconds / v.config.control_period)):
        if k % 20 == 0:
            sp = np.array([rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-1, 1),
                           rng.uniform(-2, 2)])
        cmd = sp.copy()
        z = v.estimate.position[2]
        if z < 6.0:
            cmd[2] = abs(cmd[2]) + 0.3
        elif z > 14.0:
            cmd[2] = -abs(cmd[2]) - 0.3
        v.step(cmd)
        t, e = v.truth, v.estimate
        for key, val in (("tp", t.position), ("tv", t.velocity), ("ty", t.rpy[2]),
                         ("ep", e.position), ("ev", e.velocity), ("ey", e.yaw)):
            rows[key].append(np.copy(val))
    return {k: np.array(val) for k, val in rows.items()}


@pytest.mark.parametrize("seed", [0, 1])
def test_estimate_rms_in_random_flight(vehicle: Vehicle, seed: int) -> None:
    tr = _random_flight(vehicle, seed)
    pos_rms = math.sqrt(((tr["ep"] - tr["tp"]) ** 2).sum(axis=1).mean())
    vel_rms = math.sqrt(((tr["ev"] - tr["tv"]) ** 2).sum(axis=1).mean())
    yaw_err = np.remainder(tr["ey"] - tr["ty"] + math.pi, 2 * math.pi) - math.pi
    assert pos_rms < 0.5
    assert vel_rms < 0.3
    assert math.sqrt((yaw_err**2).mean()) < 0.05
    # the flight really moved: speeds up to the limits, yaw through full turns
    assert np.abs(tr["tv"][:, :2]).max() > 1.8
    assert np.ptp(np.unwrap(tr["ty"])) > 2 * math.pi


def test_accelerometer_bias_is_estimated(vehicle: Vehicle) -> None:
    vehicle.reset(np.array([0.0, 0.0, 10.0]), 0.0, seed=3)
    vehicle.sensors.accel_bias = (0.15, -0.1, 0.08)
    for _ in range(400):
        vehicle.step(np.zeros(4))
    assert np.allclose(vehicle.estimator.bias, (0.15, -0.1, 0.08), atol=0.03)


def test_estimator_at_rest_with_perfect_sensors_stays_put() -> None:
    est = Estimator(0.1, gravity=9.8)
    est.reset((1.0, 2.0, 3.0), 0.5)
    for _ in range(100):
        for _ in range(5):
            est.propagate((0.0, 0.0, 9.8), (0.0, 0.0, 0.0), 0.0, 0.0, 0.02)
        est.correct((1.0, 2.0, 3.0, 0.0, 0.0, 0.0), 3.0, 0.5)
    assert np.allclose(est.pos, (1.0, 2.0, 3.0), atol=1e-9)
    assert np.allclose(est.vel, 0.0, atol=1e-9)
    assert est.yaw == pytest.approx(0.5, abs=1e-12)


def test_sensor_noise_seeded_and_sized() -> None:
    a, b, c = Sensors(seed=4), Sensors(seed=4), Sensors(seed=5)
    fixes = [a.gps((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)) for _ in range(4000)]
    assert fixes == [b.gps((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)) for _ in range(4000)]
    assert fixes[:10] != [c.gps((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)) for _ in range(10)]
    std = np.array(fixes).std(axis=0)
    g = a.config.gps
    assert np.allclose(std, [g.pos_noise_h] * 2 + [g.pos_noise_v] + [g.vel_noise] * 3, rtol=0.1)
    gyro = np.array([a.gyro(0.0, 0.0, 0.0) for _ in range(4000)])
    assert np.allclose(gyro.mean(axis=0), a.gyro_bias, atol=0.001)
    assert np.allclose(gyro.std(axis=0), a.config.imu.gyro_noise, rtol=0.1)


def test_same_seed_same_trajectory_bit_for_bit(vehicle: Vehicle) -> None:
    def flight(v: Vehicle, seed: int) -> np.ndarray:
        v.reset(np.array([1.0, 2.0, 5.0]), 0.3, seed=seed)
        rng = np.random.default_rng(7)
        out = []
        for _ in range(150):
            v.step(rng.uniform(-2.0, 2.0, 4) * [1.0, 1.0, 0.3, 1.0])
            t, e = v.truth, v.estimate
            out.append(np.r_[t.position, t.velocity, t.rpy, t.rotation.ravel(), t.time,
                             e.position, e.velocity, e.yaw])
        return np.array(out)

    first = flight(vehicle, 11)
    other = Vehicle(seed=99)
    assert np.array_equal(flight(other, 11), first)  # a fresh vehicle
    assert np.array_equal(flight(vehicle, 11), first)  # the same one, after other flights
    assert not np.array_equal(flight(vehicle, 12), first)  # another seed differs
