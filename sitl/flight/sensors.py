"""Sensor models: IMU (accelerometer + gyro), GPS, barometer and a heading magnetometer.

Each sensor adds seeded Gaussian noise (and, for the IMU, a constant bias drawn once per
`reset`) to ground truth handed in by the caller as plain floats.  Noise comes from one
`numpy.random.Generator`, drawn in blocks of standard normals and consumed one number at a
time, so a sample costs a few hundred nanoseconds instead of a numpy call, and the same
seed gives the same noise sequence bit for bit.

Frames: IMU readings are in the body FLU frame; GPS is world ENU; the barometer reports
height above the world datum; the magnetometer is reduced to a noisy ENU yaw.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ImuConfig:
    accel_noise: float = 0.05  # m/s^2, per sample (one per outer-loop tick)
    accel_bias: float = 0.03  # m/s^2, std of the per-axis constant bias
    gyro_noise: float = 0.005  # rad/s, per sample
    gyro_bias: float = 0.002  # rad/s, std of the per-axis constant bias


@dataclass
class GpsConfig:
    rate_hz: float = 10.0
    pos_noise_h: float = 0.3  # m, east and north
    pos_noise_v: float = 0.5  # m, up
    vel_noise: float = 0.05  # m/s, per axis (u-blox M8 class: 0.05 m/s)


@dataclass
class BaroConfig:
    noise: float = 0.1  # m


@dataclass
class MagConfig:
    yaw_noise: float = 0.02  # rad


@dataclass
class SensorConfig:
    imu: ImuConfig = field(default_factory=ImuConfig)
    gps: GpsConfig = field(default_factory=GpsConfig)
    baro: BaroConfig = field(default_factory=BaroConfig)
    mag: MagConfig = field(default_factory=MagConfig)


class _Normals:
    """Standard normal numbers from a seeded Generator, drawn a block at a time."""

    def __init__(self, seed: int, block: int = 4096) -> None:
        self._rng = np.random.default_rng(seed)
        self._block = block
        self._buf: list[float] = []
        self._i = 0

    def next(self) -> float:
        i = self._i
        if i == len(self._buf):
            self._buf = self._rng.standard_normal(self._block).tolist()
            i = 0
        self._i = i + 1
        return self._buf[i]


class Sensors:
    """IMU, GPS, barometer and magnetometer sharing one seeded noise stream."""

    def __init__(self, config: SensorConfig | None = None, seed: int = 0) -> None:
        self.config = config or SensorConfig()
        self._n = _Normals(seed)
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        """Draw new IMU biases; restart the noise stream from `seed` if one is given."""
        if seed is not None:
            self._n = _Normals(seed)
        n = self._n.next
        imu = self.config.imu
        self.accel_bias = (imu.accel_bias * n(), imu.accel_bias * n(), imu.accel_bias * n())
        self.gyro_bias = (imu.gyro_bias * n(), imu.gyro_bias * n(), imu.gyro_bias * n())

    def accel(self, fx: float, fy: float, fz: float) -> tuple[float, float, float]:
        """Accelerometer: specific force (FLU, m/s^2) plus bias and noise."""
        n, s, b = self._n.next, self.config.imu.accel_noise, self.accel_bias
        return fx + b[0] + s * n(), fy + b[1] + s * n(), fz + b[2] + s * n()

    def gyro(self, p: float, q: float, r: float) -> tuple[float, float, float]:
        """Gyro: body rates (FLU, rad/s) plus bias and noise."""
        n, s, b = self._n.next, self.config.imu.gyro_noise, self.gyro_bias
        return p + b[0] + s * n(), q + b[1] + s * n(), r + b[2] + s * n()

    def gps(self, pos: tuple[float, float, float], vel: tuple[float, float, float]
            ) -> tuple[float, float, float, float, float, float]:
        """GPS fix: ENU position and velocity with white Gaussian noise."""
        n, c = self._n.next, self.config.gps
        h, v, w = c.pos_noise_h, c.pos_noise_v, c.vel_noise
        return (pos[0] + h * n(), pos[1] + h * n(), pos[2] + v * n(),
                vel[0] + w * n(), vel[1] + w * n(), vel[2] + w * n())

    def baro(self, up: float) -> float:
        """Barometric height above the datum, m."""
        return up + self.config.baro.noise * self._n.next()

    def mag_yaw(self, yaw: float) -> float:
        """Heading from the magnetometer as an ENU yaw in (-pi, pi]."""
        return math.remainder(yaw + self.config.mag.yaw_noise * self._n.next(), 2.0 * math.pi)
