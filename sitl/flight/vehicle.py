"""The simulated vehicle: JSBSim F450 + velocity autopilot + sensors + estimator.

`Vehicle.step(setpoint)` advances one control period (0.1 s = 50 physics steps at 500 Hz
by default).  Inside it the outer loop runs `outer_hz` times a second (default 50 Hz, so
5 ticks of 10 physics steps): sample the IMU, propagate the estimate, run the velocity
autopilot on the ESTIMATE and hand its tilt/collective/yaw-rate command to the inner loops
in JSBSim.  At the end of the period GPS, barometer and magnetometer are sampled and the
Kalman filter corrects the estimate.  Ground truth (`truth`) is kept for evaluation and
collision checks; the autopilot never sees it, except the roll/pitch attitude an ideal
AHRS would give.

Deterministic: the sensor noise is the only randomness and comes from the seed; JSBSim is
re-initialised on every `reset`, so the same seed gives the same trajectory bit for bit.
Frames and units as docs/interfaces.md: SI, world ENU, body FLU.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bus.params import default
from sitl.flight.autopilot import AutopilotConfig, VelocityAutopilot
from sitl.flight.estimator import Estimator, EstimatorConfig
from sitl.flight.flight_model import FlightModel, enu_rpy, rotation_flu_to_enu
from sitl.flight.sensors import SensorConfig, Sensors


@dataclass
class VehicleConfig:
    physics_hz: float = 500.0
    control_period: float = 0.1
    max_speed_xy: float = default("MPC_XY_VEL_MAX")  # m/s per axis, setpoints saturated
    max_speed_z: float = default("MPC_Z_VEL_MAX")
    max_yaw_rate: float = 2.0  # rad/s
    outer_hz: float = 50.0  # autopilot + estimator propagation rate
    autopilot: AutopilotConfig = field(default_factory=AutopilotConfig)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)


@dataclass
class VehicleState:
    """Ground truth."""

    position: np.ndarray  # (3,) ENU
    velocity: np.ndarray  # (3,) ENU
    rpy: np.ndarray  # (3,) roll, pitch (nose down +), yaw (ENU, 0 = east, CCW +)
    rotation: np.ndarray  # (3,3) body(FLU) -> world(ENU)
    time: float


@dataclass
class EstimatedState:
    position: np.ndarray  # (3,) ENU
    velocity: np.ndarray  # (3,) ENU
    yaw: float


class Vehicle:
    """One simulated F450 flown by velocity setpoints (vx_east, vy_north, vz_up, yaw_rate)."""

    def __init__(self, config: VehicleConfig | None = None, seed: int = 0) -> None:
        self.config = c = config or VehicleConfig()
        steps = c.physics_hz * c.control_period
        outer = c.outer_hz * c.control_period
        if abs(steps - round(steps)) > 1e-9 or abs(outer - round(outer)) > 1e-9:
            raise ValueError("control_period must hold whole physics steps and outer ticks")
        self._n_outer = round(outer)
        self._n_inner, rem = divmod(round(steps), self._n_outer)
        if rem:
            raise ValueError("physics_hz must be a multiple of outer_hz")
        self._dt_outer = self._n_inner / c.physics_hz
        self.fm = FlightModel(c.physics_hz, hover_throttle=c.autopilot.hover_throttle)
        self.autopilot = VelocityAutopilot(c.autopilot, c.max_speed_xy, c.max_speed_z,
                                           c.max_yaw_rate)
        self.sensors = Sensors(c.sensors, seed)
        self.estimator = Estimator(c.control_period, config=c.estimator)
        self.rejected_setpoints = 0
        self.reset(np.array([0.0, 0.0, 3.5]), 0.0, seed)

    def reset(self, position: np.ndarray, yaw: float, seed: int | None = None,
              on_ground: bool = False) -> None:
        """Airborne, hovering (zero velocity) at `position` (ENU) facing `yaw`; with
        ``on_ground``, standing on flat ground at ``position[2]``, motors stopped.

        Re-seeds the sensor noise if `seed` is given (otherwise the noise stream goes on);
        clears the autopilot, the estimator and `rejected_setpoints`.
        """
        e, n, u = (float(x) for x in position)
        self.fm.reset(e, n, u, float(yaw), on_ground=on_ground)
        g = self.fm.gravity
        self.sensors.reset(seed)
        self.autopilot.reset(gravity=g)
        self.estimator.reset(self.fm.position() if on_ground else (e, n, u), float(yaw),
                             gravity=g)
        self.rejected_setpoints = 0
        self._steps = 0
        self._truth: VehicleState | None = None

    def step(self, setpoint: np.ndarray, motors: bool = True) -> None:
        """Fly one control period toward the ENU velocity/yaw-rate `setpoint`;
        ``motors`` False: motors stopped (disarmed or idle on the ground), the autopilot
        is reset and the setpoint ignored."""
        vx, vy, vz, yaw_rate = setpoint  # ValueError unless exactly four values
        if not motors:
            self._step_motors_off()
            return
        if not self.autopilot.set_setpoint(vx, vy, vz, yaw_rate):
            self.rejected_setpoints += 1
        fm, sens, est, ap = self.fm, self.sensors, self.estimator, self.autopilot
        dt, n_inner = self._dt_outer, self._n_inner
        specific_force, gyro, rpy = fm.specific_force_flu, fm.gyro_flu, fm.rpy
        set_commands, run = fm.set_commands, fm.run
        for _ in range(self._n_outer):
            f = sens.accel(*specific_force())
            w = sens.gyro(*gyro())
            roll, pitch, _ = rpy()  # the AHRS attitude (ideal)
            est.propagate(f, w, roll, pitch, dt)
            set_commands(*ap.update(est.pos, est.vel, dt))
            run(n_inner)
        pos = fm.position()
        est.correct(sens.gps(pos, fm.velocity()), sens.baro(pos[2]), sens.mag_yaw(rpy()[2]))
        self._steps += 1
        self._truth = None

    def _step_motors_off(self) -> None:
        fm, sens, est = self.fm, self.sensors, self.estimator
        self.autopilot.reset(gravity=fm.gravity)
        fm.set_commands(0.0, 0.0, 0.0, 0.0)
        for _ in range(self._n_outer):
            f = sens.accel(*fm.specific_force_flu())
            w = sens.gyro(*fm.gyro_flu())
            roll, pitch, _ = fm.rpy()
            est.propagate(f, w, roll, pitch, self._dt_outer)
            fm.run(self._n_inner)
        pos = fm.position()
        est.correct(sens.gps(pos, fm.velocity()), sens.baro(pos[2]), sens.mag_yaw(fm.rpy()[2]))
        self._steps += 1
        self._truth = None

    def set_ground(self, elevation: float) -> None:
        """Move the flight model's flat ground (see :mod:`sitl.flight.flight_model`)."""
        self.fm.set_ground(elevation)

    @property
    def time(self) -> float:
        """Simulated seconds since the last reset."""
        return self._steps * self.config.control_period

    @property
    def truth(self) -> VehicleState:
        """Ground truth at the end of the last step (cached until the next step: read-only)."""
        if self._truth is None:
            phi, theta, psi = self.fm.euler_ned()
            self._truth = VehicleState(
                position=np.array(self.fm.position()),
                velocity=np.array(self.fm.velocity()),
                rpy=np.array(enu_rpy(phi, theta, psi)),
                rotation=np.array(rotation_flu_to_enu(phi, theta, psi)),
                time=self.time,
            )
        return self._truth

    @property
    def estimate(self) -> EstimatedState:
        """What the vehicle believes (the autopilot flies on this), as fresh arrays."""
        est = self.estimator
        return EstimatedState(position=np.array(est.pos), velocity=np.array(est.vel),
                              yaw=est.yaw)
