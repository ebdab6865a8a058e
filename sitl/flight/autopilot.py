"""Velocity autopilot for the F450, in the style of PX4's multicopter control cascade.

Cascade (outer loops here in Python, inner loops in JSBSim):

1. Setpoint ``(vx, vy, vz, yaw_rate)`` in world ENU: NaN/inf setpoints are rejected (the
   last valid one holds, ``rejected`` counts them); valid ones are saturated per axis to
   the configured limits.
2. Velocity PI per world axis -> acceleration setpoint, as PX4's ``PositionControl``:
   horizontal acceleration limited in norm, vertical acceleration clamped, integrators
   with conditional-integration anti-windup (an axis stops integrating while its output
   is saturated in the direction of its error) and a clamp on the integral.
3. Acceleration -> thrust vector: the collective is ``hover * sqrt(|a - g| / g)`` (the
   F450's thrust grows about with the square of the throttle; measured hover 0.4068 at
   sea level) and the tilt vector is ``a_horizontal / (g + a_up)``, limited to
   ``max_tilt_deg``.  PX4's "position lock" is kept for a zero setpoint: when the
   horizontal (or vertical) setpoint is exactly zero and the estimated speed has dropped
   below ``hold_speed``, the estimated position is latched and a P loop on it feeds the
   velocity loop, so the vehicle hovers in place instead of drifting with the estimate.
4. Tilt vector + yaw rate -> attitude setpoint -> body-rate references -> the F450 rate
   PIDs and mixer: these run inside JSBSim at every physics step
   (``sitl/flight/fcs/f450_attitude_rate.xml``; see :mod:`sitl.flight.flight_model`).

Outer-loop rate (``VehicleConfig.outer_hz``; it must divide the 0.1 s control period
into whole ticks: 10, 20, 50 or 100 Hz).  Measured on this 2-core machine, rates
interleaved round-robin, 9 x 1,000 random-setpoint control steps each, best / median
(the other core was busy, so medians run ~20 % low); JSBSim alone with the skyloop FCS:
3,117 / 2,501 control steps/s (156k / 125k physics steps/s):
    10 Hz: 2,521 / 2,103 control steps/s; velocity-estimate RMS 0.08 m/s
    20 Hz: 2,329 / 1,851;  velocity-estimate RMS 0.05 m/s, vz-step overshoot 12 %
    50 Hz: 2,203 / 1,656;  velocity-estimate RMS 0.03 m/s, vz-step overshoot 9 %
   100 Hz: 1,962 / 1,523;  no better than 50 Hz
The step responses hardly depend on the rate (t90 0.7-0.9 s for 2 m/s and 1 m/s steps)
because the attitude loop already runs at 500 Hz inside JSBSim; what the rate buys is
the estimator's IMU sampling.  Default: 50 Hz (5 ticks per control period), whose
Python share is ~0.14 ms per control step (the DESIGN.md budget is 0.3 ms).  Per tick
everything is plain-float math (~6 us: property reads, IMU noise, estimator
propagation, this loop); the Kalman predict/update (~34 us) runs once per period.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from bus.params import default

log = logging.getLogger(__name__)


@dataclass
class AutopilotConfig:
    kp_xy: float = 2.5  # 1/s, horizontal velocity P gain
    ki_xy: float = 0.3  # 1/s^2
    kp_z: float = 3.0
    ki_z: float = 1.5
    max_accel_xy: float = 4.0  # m/s^2 (norm)
    max_accel_up: float = 4.0  # m/s^2
    max_accel_down: float = 3.0  # m/s^2
    max_int_xy: float = 2.0  # m/s^2, clamp on each horizontal integral
    max_int_z: float = 3.0
    max_tilt_deg: float = 30.0
    hover_throttle: float = 0.4068  # measured: specific force = g at sea level
    max_throttle: float = 0.85  # headroom left for the attitude loop
    hold_position: bool = True  # PX4-style position lock on a zero setpoint
    hold_gain: float = 1.0  # 1/s, position error -> velocity
    hold_speed: float = 0.3  # m/s, lock engages below this estimated speed


class VelocityAutopilot:
    """Setpoint validation and the velocity -> acceleration -> thrust-vector loops."""

    def __init__(self, config: AutopilotConfig | None = None,
                 max_speed_xy: float = default("MPC_XY_VEL_MAX"),
                 max_speed_z: float = default("MPC_Z_VEL_MAX"), max_yaw_rate: float = 2.0,
                 gravity: float = 9.80665) -> None:
        self.config = config or AutopilotConfig()
        self.max_speed_xy = max_speed_xy
        self.max_speed_z = max_speed_z
        self.max_yaw_rate = max_yaw_rate
        self.gravity = gravity
        self.rejected = 0
        self.reset()

    def reset(self, gravity: float | None = None) -> None:
        """Zero setpoint (hover), empty integrators, no position lock."""
        if gravity is not None:
            self.gravity = gravity
        self.setpoint = (0.0, 0.0, 0.0, 0.0)
        self._ix = self._iy = self._iz = 0.0
        self._lock_xy: tuple[float, float] | None = None
        self._lock_z: float | None = None

    def set_setpoint(self, vx: float, vy: float, vz: float, yaw_rate: float) -> bool:
        """Validate and saturate a setpoint; False (and counted) if any value is not finite.

        A rejected setpoint leaves the last valid one in force.  Rejections are logged at
        WARNING on the 1st, 2nd, 4th, 8th, ... occurrence, so a stream of bad input
        cannot flood the log.
        """
        try:
            vals = (float(vx), float(vy), float(vz), float(yaw_rate))
            ok = all(map(math.isfinite, vals))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            self.rejected += 1
            if self.rejected & (self.rejected - 1) == 0:
                log.warning("rejected non-finite velocity setpoint %r (%d rejected so far); "
                            "holding %r", (vx, vy, vz, yaw_rate), self.rejected, self.setpoint)
            return False
        mxy, mz, mr = self.max_speed_xy, self.max_speed_z, self.max_yaw_rate
        self.setpoint = (min(max(vals[0], -mxy), mxy), min(max(vals[1], -mxy), mxy),
                         min(max(vals[2], -mz), mz), min(max(vals[3], -mr), mr))
        return True

    def update(self, pos: tuple[float, float, float], vel: tuple[float, float, float],
               dt: float) -> tuple[float, float, float, float]:
        """One outer-loop tick on the estimated state.

        Returns the inner-loop command (tilt_east, tilt_north, throttle, yaw_rate).
        """
        c = self.config
        vx_sp, vy_sp, vz_sp, yaw_rate = self.setpoint
        vx, vy, vz = vel

        # position lock on a zero setpoint (PX4 position-mode behaviour)
        if c.hold_position and vx_sp == 0.0 and vy_sp == 0.0:
            if self._lock_xy is None and vx * vx + vy * vy < c.hold_speed * c.hold_speed:
                self._lock_xy = (pos[0], pos[1])
            if self._lock_xy is not None:
                vx_sp = c.hold_gain * (self._lock_xy[0] - pos[0])
                vy_sp = c.hold_gain * (self._lock_xy[1] - pos[1])
                s = math.hypot(vx_sp, vy_sp)
                if s > self.max_speed_xy:
                    vx_sp *= self.max_speed_xy / s
                    vy_sp *= self.max_speed_xy / s
        else:
            self._lock_xy = None
        if c.hold_position and vz_sp == 0.0:
            if self._lock_z is None and abs(vz) < c.hold_speed:
                self._lock_z = pos[2]
            if self._lock_z is not None:
                vz_sp = min(max(c.hold_gain * (self._lock_z - pos[2]), -self.max_speed_z),
                            self.max_speed_z)
        else:
            self._lock_z = None

        # velocity PI -> acceleration setpoint
        ex, ey, ez = vx_sp - vx, vy_sp - vy, vz_sp - vz
        ax = c.kp_xy * ex + self._ix
        ay = c.kp_xy * ey + self._iy
        az = c.kp_z * ez + self._iz
        sat_xy = False
        a_h = math.hypot(ax, ay)
        if a_h > c.max_accel_xy:
            ax *= c.max_accel_xy / a_h
            ay *= c.max_accel_xy / a_h
            sat_xy = True
        sat_z = 0
        if az > c.max_accel_up:
            az, sat_z = c.max_accel_up, 1
        elif az < -c.max_accel_down:
            az, sat_z = -c.max_accel_down, -1

        # anti-windup: integrate only while not pushing further into saturation
        mi = c.max_int_xy
        if not (sat_xy and ex * ax > 0.0):
            self._ix = min(max(self._ix + c.ki_xy * ex * dt, -mi), mi)
        if not (sat_xy and ey * ay > 0.0):
            self._iy = min(max(self._iy + c.ki_xy * ey * dt, -mi), mi)
        if not (sat_z * ez > 0.0):
            self._iz = min(max(self._iz + c.ki_z * ez * dt, -c.max_int_z), c.max_int_z)

        # acceleration -> tilt vector and collective
        g = self.gravity
        up = g + az
        tilt_e, tilt_n = ax / up, ay / up
        t = math.hypot(tilt_e, tilt_n)
        t_max = math.tan(math.radians(c.max_tilt_deg))
        if t > t_max:
            tilt_e *= t_max / t
            tilt_n *= t_max / t
            t = t_max
        thrust = up * math.sqrt(1.0 + t * t)
        throttle = min(c.hover_throttle * math.sqrt(thrust / g), c.max_throttle)
        return tilt_e, tilt_n, throttle, yaw_rate
