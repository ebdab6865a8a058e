"""The commander's guidance: what OFFBOARD and RTL fly, and the land detector.

Pure functions of the commander's parameters (:class:`~sitl.commander.types.CommanderConfig`)
and the vehicle's sample, kept apart from the state machine in :mod:`sitl.commander.machine`
(which owns every transition and event). No I/O, no clock.
"""

from __future__ import annotations

import math

from sitl.commander.types import EPS, CommanderConfig, Setpoint, VehicleSample


def detect_landing(config: CommanderConfig, low_since: float | None, landed: bool,
                   now: float, sample: VehicleSample) -> tuple[float | None, bool]:
    """The land detector, one step: landed once the height above ground and the vertical
    speed have stayed under ``land_detect_height`` / ``land_detect_speed`` for
    ``land_detect_time``; airborne as soon as either is exceeded. Returns (since when
    both hold, None: they do not; landed)."""
    c = config
    if not (sample.height_agl <= c.land_detect_height and abs(sample.vz) <= c.land_detect_speed):
        return None, False
    if low_since is None:
        low_since = now
    return low_since, landed or now - low_since >= c.land_detect_time - EPS


def offboard_setpoint(sp: tuple[float, float, float, float], body: bool,
                      yaw_target: float | None, yaw: float,
                      config: CommanderConfig) -> Setpoint:
    """The newest OFFBOARD setpoint as world ENU velocity + yaw rate: a body-frame one
    (forward, left, up) rotated by the vehicle's ``yaw``, with the same arithmetic as
    ``sitl.episode.body_to_world``, operation for operation; an absolute heading target
    becomes ``yaw_gain * wrap(target - yaw)``, clamped to ``max_yaw_rate``."""
    vx, vy, vz, yaw_rate = sp
    if body:
        cy, sy = math.cos(yaw), math.sin(yaw)
        vx, vy = cy * vx - sy * vy, sy * vx + cy * vy
    if yaw_target is not None:
        err = (yaw_target - yaw + math.pi) % (2.0 * math.pi) - math.pi
        yaw_rate = max(-config.max_yaw_rate, min(config.max_yaw_rate, config.yaw_gain * err))
    return Setpoint(vx, vy, vz, yaw_rate)


def rtl_setpoint(config: CommanderConfig, phase: str, rtl_z: float,
                 home: tuple[float, float], sample: VehicleSample,
                 landed: bool) -> tuple[str, Setpoint | None]:
    """One RTL step: climb to ``rtl_z``, fly home holding it, descend (see
    :mod:`sitl.commander.machine`). Returns the phase after this step (``"climb"``,
    ``"return"``, ``"descend"``) and the setpoint; None once descended and ``landed``
    (the commander then disarms)."""
    c = config
    hold_z = max(-c.rtl_climb_speed, min(c.rtl_climb_speed, c.rtl_gain * (rtl_z - sample.z)))
    if phase == "climb":
        if rtl_z - sample.z > c.takeoff_tolerance:
            return phase, Setpoint(0.0, 0.0, hold_z, 0.0)
        phase = "return"
    if phase == "return":
        dx, dy = home[0] - sample.x, home[1] - sample.y
        dist = math.hypot(dx, dy)
        if dist > c.rtl_arrive_radius:
            speed = min(c.rtl_speed, c.rtl_gain * dist)
            return phase, Setpoint(speed * dx / dist, speed * dy / dist, hold_z, 0.0)
        phase = "descend"
    if landed:
        return phase, None
    return phase, Setpoint(0.0, 0.0, -c.land_speed, 0.0)
