"""ENU <-> NED: the one place where skyloop's frames meet MAVLink's.

skyloop (simulator, perception, policy) works in:

* world **ENU**: x east, y north, z up; yaw counter-clockwise (seen from above) from
  east, yaw rate positive counter-clockwise;
* body **FLU**: x forward, y left, z up (REP 103). Euler angles of a FLU body in ENU are
  the ZYX angles (yaw, pitch, roll) of ``R_enu_flu = Rz(yaw) Ry(pitch) Rx(roll)``, so
  pitch is positive nose *down* (as ``sitl.flight.vehicle.VehicleState.rpy``) and roll is
  positive right side down.

MAVLink / PX4 works in:

* world **NED**: x north, y east, z down; yaw clockwise from north;
* body **FRD** (``MAV_FRAME_BODY_NED`` for velocity setpoints: forward, right, down,
  rotated by the heading only); ZYX Euler angles of ``R_ned_frd``, pitch positive nose
  *up*, roll positive right side down.

Every conversion is its own inverse (the frame changes are reflections/rotations by
pi), so each pair below is one function under two names; yaw is wrapped to
``[-pi, pi)``. Quaternions are Hamilton ``(w, x, y, z)`` (MAVLink ATTITUDE_QUATERNION's
q1..q4), body -> world. Plain floats in, plain floats out: no numpy, cheap per message.
"""

from __future__ import annotations

import math

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]

_SQRT_HALF = math.sqrt(0.5)


def wrap_pi(angle: float) -> float:
    """Wrap an angle to ``[-pi, pi)``."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


# ------------------------------------------------------------------ world vectors
def enu_to_ned(x: float, y: float, z: float) -> Vec3:
    """A world vector (position, velocity, acceleration) from ENU to NED."""
    return (y, x, -z)


def ned_to_enu(x: float, y: float, z: float) -> Vec3:
    """A world vector from NED to ENU (the same swap: the map is its own inverse)."""
    return (y, x, -z)


# ------------------------------------------------------------------ body vectors
def flu_to_frd(x: float, y: float, z: float) -> Vec3:
    """A body vector from forward-left-up to forward-right-down (MAVLink BODY_NED)."""
    return (x, -y, -z)


def frd_to_flu(x: float, y: float, z: float) -> Vec3:
    """A body vector from forward-right-down (MAVLink BODY_NED) to forward-left-up."""
    return (x, -y, -z)


# ------------------------------------------------------------------ heading
def yaw_enu_to_ned(yaw: float) -> float:
    """Heading: CCW from east (ENU) -> CW from north (NED), wrapped to [-pi, pi)."""
    return wrap_pi(0.5 * math.pi - yaw)


def yaw_ned_to_enu(yaw: float) -> float:
    """Heading: CW from north (NED) -> CCW from east (ENU), wrapped to [-pi, pi)."""
    return wrap_pi(0.5 * math.pi - yaw)


def yaw_rate_enu_to_ned(rate: float) -> float:
    """Yaw rate: CCW-positive (z up) -> CW-positive (z down)."""
    return -rate


def yaw_rate_ned_to_enu(rate: float) -> float:
    """Yaw rate: CW-positive (z down) -> CCW-positive (z up)."""
    return -rate


# ------------------------------------------------------------------ attitude
def euler_enu_to_ned(roll: float, pitch: float, yaw: float) -> Vec3:
    """ZYX Euler angles of a FLU body in ENU -> of the FRD body in NED (roll, pitch, yaw)."""
    return (roll, -pitch, yaw_enu_to_ned(yaw))


def euler_ned_to_enu(roll: float, pitch: float, yaw: float) -> Vec3:
    """ZYX Euler angles of a FRD body in NED -> of the FLU body in ENU (roll, pitch, yaw)."""
    return (roll, -pitch, yaw_ned_to_enu(yaw))


def body_rates_flu_to_frd(p: float, q: float, r: float) -> Vec3:
    """Body angular rates FLU -> FRD (rollspeed, pitchspeed, yawspeed of ATTITUDE)."""
    return (p, -q, -r)


def body_rates_frd_to_flu(p: float, q: float, r: float) -> Vec3:
    """Body angular rates FRD -> FLU."""
    return (p, -q, -r)


def quat_enu_to_ned(q: Quat) -> Quat:
    """Attitude quaternion body FLU -> world ENU  to  body FRD -> world NED.

    ``q_ned_frd = q_(ned<-enu) * q_enu_flu * q_(flu<-frd)`` with ``q_(ned<-enu) =
    (0, s, s, 0)`` (pi about the north-east diagonal), ``q_(flu<-frd) = (0, 1, 0, 0)``
    (pi about x), ``s = sqrt(1/2)``; expanded, up to the sign, which is normalised to
    ``w >= 0``.
    """
    w, x, y, z = q
    out = (_SQRT_HALF * (w + z), _SQRT_HALF * (x + y), _SQRT_HALF * (x - y),
           _SQRT_HALF * (w - z))
    return out if out[0] >= 0.0 else (-out[0], -out[1], -out[2], -out[3])


def quat_ned_to_enu(q: Quat) -> Quat:
    """Attitude quaternion body FRD -> world NED  to  body FLU -> world ENU (same map)."""
    return quat_enu_to_ned(q)


def quat_from_euler(roll: float, pitch: float, yaw: float) -> Quat:
    """Hamilton quaternion of the ZYX rotation ``Rz(yaw) Ry(pitch) Rx(roll)``, ``w >= 0``."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    q = (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
         cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)
    return q if q[0] >= 0.0 else (-q[0], -q[1], -q[2], -q[3])


def euler_from_quat(q: Quat) -> Vec3:
    """ZYX Euler angles ``(roll, pitch, yaw)`` of a Hamilton quaternion (any frame pair)."""
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return (roll, pitch, yaw)


# ------------------------------------------------------------------ velocity setpoints
def velocity_enu_to_local_ned(vx: float, vy: float, vz: float, yaw_rate: float) -> tuple[
        float, float, float, float]:
    """World velocity + yaw rate, ENU -> MAV_FRAME_LOCAL_NED fields (vx, vy, vz, yaw_rate)."""
    n, e, d = enu_to_ned(vx, vy, vz)
    return (n, e, d, yaw_rate_enu_to_ned(yaw_rate))


def velocity_local_ned_to_enu(vx: float, vy: float, vz: float, yaw_rate: float) -> tuple[
        float, float, float, float]:
    """MAV_FRAME_LOCAL_NED (vx, vy, vz, yaw_rate) -> world ENU velocity + CCW yaw rate."""
    e, n, u = ned_to_enu(vx, vy, vz)
    return (e, n, u, yaw_rate_ned_to_enu(yaw_rate))


def velocity_flu_to_body_ned(vx: float, vy: float, vz: float, yaw_rate: float) -> tuple[
        float, float, float, float]:
    """Body-horizontal FLU velocity + CCW yaw rate -> MAV_FRAME_BODY_NED fields."""
    f, r, d = flu_to_frd(vx, vy, vz)
    return (f, r, d, yaw_rate_enu_to_ned(yaw_rate))


def velocity_body_ned_to_flu(vx: float, vy: float, vz: float, yaw_rate: float) -> tuple[
        float, float, float, float]:
    """MAV_FRAME_BODY_NED (forward, right, down, yaw_rate) -> body-horizontal FLU + CCW rate."""
    f, left, u = frd_to_flu(vx, vy, vz)
    return (f, left, u, yaw_rate_ned_to_enu(yaw_rate))


# ------------------------------------------------------------------ local <-> geodetic
# The vehicle's local ENU origin sits at a geodetic point (VehicleLinkConfig.origin, PX4
# SITL's default 47.397742 N, 8.545594 E, 488 m AMSL). Flat earth (equirectangular about
# the origin, WGS-84 equatorial radius): error ~ d^2 / R, under a millimetre within 2 km,
# far below what skyloop's scenarios span. Used for GLOBAL_POSITION_INT, GPS_RAW_INT,
# HOME_POSITION, and to turn mission/fence/rally lat/lon into local goals.
EARTH_RADIUS_M = 6378137.0
Geodetic = tuple[float, float, float]  # latitude deg, longitude deg, altitude m AMSL


def enu_to_geodetic(east: float, north: float, up: float, origin: Geodetic) -> Geodetic:
    """Local ENU metres about ``origin`` -> (lat deg, lon deg, alt m AMSL), flat earth."""
    lat0, lon0, alt0 = origin
    lat = lat0 + math.degrees(north / EARTH_RADIUS_M)
    lon = lon0 + math.degrees(east / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
    return (lat, lon, alt0 + up)


def geodetic_to_enu(lat: float, lon: float, alt: float, origin: Geodetic) -> Vec3:
    """(lat deg, lon deg, alt m AMSL) -> local ENU metres about ``origin`` (the inverse of
    :func:`enu_to_geodetic`)."""
    lat0, lon0, alt0 = origin
    north = math.radians(lat - lat0) * EARTH_RADIUS_M
    east = math.radians(lon - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
    return (east, north, alt - alt0)
