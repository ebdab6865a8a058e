"""The commander's vocabulary: states, parameters, verdicts, samples, setpoints, events.

Kept apart from :mod:`sitl.commander.machine` (the state machine) so each stays small; import
them from either module. Pure: no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import NamedTuple

from bus.params import default

EPS = 1e-9  # s, tolerance on time comparisons (float sums of control periods)


class State(StrEnum):
    """Commander states; the values are the names the MAVLink bridge maps to PX4 modes."""

    DISARMED = "DISARMED"
    ARMED = "ARMED"  # armed, idle on the ground
    TAKEOFF = "TAKEOFF"
    OFFBOARD = "OFFBOARD"
    HOLD = "HOLD"
    LAND = "LAND"
    RTL = "RTL"  # return to home: climb, fly back, descend, touch down, disarm


@dataclass
class CommanderConfig:
    """Commander settings; PX4 names in brackets for those PX4 has that skyloop does not
    expose. Those a ground station sets are ``bus.params`` parameters (their defaults
    come from there, and ``ParamDef.sets`` names the field)."""

    setpoint_timeout: float = default("COM_OF_LOSS_T")  # s, older: OFFBOARD refused, left
    hold_before_land: float = default("SKY_HOLD_LAND_T")  # s failsafe HOLD -> LAND, inf: never
    takeoff_altitude: float = default("MIS_TAKEOFF_ALT")  # m above the takeoff point
    max_takeoff_altitude: float = 100.0  # m, larger requests are refused
    takeoff_speed: float = 1.5  # m/s [MPC_TKO_SPEED]
    takeoff_gain: float = 1.0  # 1/s, climb rate = min(takeoff_speed, gain * error)
    takeoff_tolerance: float = 0.1  # m below the target counts as reached
    land_speed: float = 0.7  # m/s [MPC_LAND_SPEED]
    land_detect_height: float = 0.1  # m above ground
    land_detect_speed: float = 0.2  # m/s, |vertical speed|
    land_detect_time: float = 0.5  # s both must hold
    disarm_preflight: float = 10.0  # s armed on the ground without takeoff [COM_DISARM_PRFLT]
    yaw_gain: float = 1.0  # 1/s, absolute heading setpoint -> yaw rate
    max_yaw_rate: float = 2.0  # rad/s, clamp of that yaw rate
    rtl_speed: float = default("MPC_XY_VEL_MAX")  # m/s, horizontal return speed
    rtl_climb_speed: float = default("MPC_Z_VEL_MAX")  # m/s, RTL climb to the flight level
    rtl_gain: float = 1.0  # 1/s, distance (m) -> approach speed (m/s) near the target
    rtl_arrive_radius: float = 0.5  # m from home: the return leg ends, descent starts
    flight_level: float = default("SKY_FLIGHT_LVL")  # m above ground for RTL
    geofence: float = default("GF_MAX_HOR_DIST")  # m horizontal from home -> RTL, 0: off


@dataclass(frozen=True)
class Verdict:
    """The answer to a request: accepted, or refused with a short reason code."""

    accepted: bool
    reason: str = ""


ACCEPTED = Verdict(True)


@dataclass(frozen=True)
class VehicleSample:
    """What the commander needs of the vehicle each step (world ENU, SI); ``x``, ``y``
    (horizontal position) are needed for home, RTL and the geofence."""

    z: float  # m, up
    vz: float  # m/s, up
    yaw: float  # rad, CCW from east
    height_agl: float  # m above the ground below the vehicle
    x: float = 0.0  # m, east
    y: float = 0.0  # m, north


class Setpoint(NamedTuple):
    """Velocity setpoint for the autopilot: world ENU m/s and CCW yaw rate rad/s."""

    vx: float
    vy: float
    vz: float
    yaw_rate: float


ZERO = Setpoint(0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class CommanderEvent:
    """A transition, failsafe or refusal: ``kind`` is ``mode``, ``failsafe``, ``rejected``
    or ``collision``; ``severity`` ``info``, ``warning`` or ``critical``; ``text`` fits
    one STATUSTEXT (<= 50 characters)."""

    time: float
    kind: str
    text: str
    severity: str
    state: State
