"""The telemetry a PX4-like vehicle streams, built from the commander and the latest state.

:class:`TelemetryReporter` builds each message from the commander (mode, arming, landed
state), the latest :class:`~mavlink_bridge.interfaces.VehicleTelemetry` (ENU/FLU, turned
into NED/FRD by :mod:`mavlink_bridge.frames` only), the geodetic origin of the local
frame and two small models kept here:

* **home**: the first reported position, then the position at each arming (as PX4);
  :meth:`TelemetryReporter.set_home` overrides it. HOME_POSITION goes out on change.
* **battery** (:class:`BatteryModel`): a 4S 5000 mAh LiPo drawing 0.5 A disarmed and
  15 A armed (an F450 hovering); remaining = 1 - drawn / capacity; voltage =
  cells x (3.5 + 0.7 x remaining) V minus 0.02 ohm x current. 20 minutes of armed
  time empties it; PX4's thresholds (15 % low, 7 % critical, 5 % emergency) give
  BATTERY_STATUS.charge_state. Integrated over the ``now`` of each poll.

GPS is ideal and reported as such (3D fix, 10 satellites, HDOP 0.8, 0.5 m horizontal
accuracy); time fields (``time_boot_ms``/``time_usec``) are the telemetry's ``time``.
Landed state (EXTENDED_SYS_STATE): TAKEOFF while the commander takes off (armed; a
takeoff waiting disarmed for arming, AUTO.TAKEOFF in the heartbeat as with PX4, is not),
else ON_GROUND when its land detector says landed, LANDING in LAND, IN_AIR otherwise. SYS_STATUS
reports gyro, accel, mag, baro, GPS, AHRS, battery, geofence (unhealthy while the
commander's ``failsafe_reason`` is ``"geofence"``) and the control loops present,
enabled and healthy, and MAV_SYS_STATUS_PREARM_CHECK healthy when the vehicle can arm
(or is armed) and no failsafe runs. VFR_HUD's airspeed is the ground speed (no wind
estimate) and its throttle is 0 disarmed, 50 % armed (no motor model here).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from mavlink_bridge import frames
from mavlink_bridge.interfaces import CommanderLike, Vec3, VehicleTelemetry
from mavlink_bridge.modes import base_mode_flags, px4_mode_for_state
from mavlink_bridge.transport import mavlink as M

_SENSORS = (M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | M.MAV_SYS_STATUS_SENSOR_3D_MAG | M.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | M.MAV_SYS_STATUS_SENSOR_GPS | M.MAV_SYS_STATUS_AHRS
            | M.MAV_SYS_STATUS_SENSOR_BATTERY | M.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
            | M.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
            | M.MAV_SYS_STATUS_SENSOR_YAW_POSITION | M.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
            | M.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
            | M.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS | M.MAV_SYS_STATUS_GEOFENCE)
PREARM = M.MAV_SYS_STATUS_PREARM_CHECK
UINT16_MAX = 65535


@dataclass
class BatteryModel:
    """A LiPo pack drained by armed time (see the module docstring)."""

    cells: int = 4
    capacity_mah: float = 5000.0
    idle_current_a: float = 0.5
    armed_current_a: float = 15.0
    resistance_ohm: float = 0.02
    drawn_mah: float = 0.0
    current_a: float = 0.5
    _last: float | None = None

    def step(self, now: float, armed: bool) -> None:
        """Integrate the current drawn since the previous call (time never runs back)."""
        self.current_a = self.armed_current_a if armed else self.idle_current_a
        if self._last is not None and now > self._last:
            self.drawn_mah += self.current_a * (now - self._last) / 3.6
        self._last = now if self._last is None else max(self._last, now)

    @property
    def remaining(self) -> float:
        return max(0.0, 1.0 - self.drawn_mah / self.capacity_mah)

    @property
    def voltage(self) -> float:
        return self.cells * (3.5 + 0.7 * self.remaining) - self.resistance_ohm * self.current_a

    @property
    def charge_state(self) -> int:
        r = self.remaining
        if r <= 0.05:
            return M.MAV_BATTERY_CHARGE_STATE_EMERGENCY
        if r <= 0.07:
            return M.MAV_BATTERY_CHARGE_STATE_CRITICAL
        if r <= 0.15:
            return M.MAV_BATTERY_CHARGE_STATE_LOW
        return M.MAV_BATTERY_CHARGE_STATE_OK


def landed_state(commander: CommanderLike) -> int:
    """MAV_LANDED_STATE from the commander (see the module docstring)."""
    state = str(commander.state)
    if state == "TAKEOFF" and commander.armed:  # disarmed: a takeoff waiting for arming
        return M.MAV_LANDED_STATE_TAKEOFF
    if commander.landed:
        return M.MAV_LANDED_STATE_ON_GROUND
    if state == "LAND":
        return M.MAV_LANDED_STATE_LANDING
    return M.MAV_LANDED_STATE_IN_AIR


def _cdeg(yaw_ned: float) -> int:
    return int(round(math.degrees(yaw_ned) * 100.0)) % 36000


class TelemetryReporter:
    """Builds HEARTBEAT, SYS_STATUS, ..., BATTERY_STATUS for the link to stream."""

    def __init__(self, commander: CommanderLike, origin: frames.Geodetic,
                 battery: BatteryModel | None = None) -> None:
        self.commander = commander
        self.origin = origin
        self.battery = battery or BatteryModel()
        self.telemetry: VehicleTelemetry | None = None
        self.home: Vec3 | None = None  # local ENU
        self.home_changed = False  # the link sends HOME_POSITION and clears this
        self._was_armed = False

    # ------------------------------------------------------------------ inputs
    def update(self, telemetry: VehicleTelemetry) -> None:
        self.telemetry = telemetry
        if self.home is None:
            self.set_home(telemetry.position)

    def set_home(self, position: Vec3) -> None:
        """Home (local ENU) from now on; HOME_POSITION follows."""
        self.home = (float(position[0]), float(position[1]), float(position[2]))
        self.home_changed = True

    @property
    def home_amsl(self) -> float:
        """Home's altitude AMSL in metres (the origin's before any position arrived)."""
        return self.origin[2] + (0.0 if self.home is None else self.home[2])

    @property
    def takeoff_amsl(self) -> float:
        """The takeoff point's altitude AMSL (m), what NAV_TAKEOFF's AMSL altitude is read
        against: on the ground, where the vehicle stands (QGroundControl sends its AMSL
        altitude + the relative one, before arming moves home there); else home's."""
        if self.telemetry is not None and self.commander.landed:
            return self.origin[2] + float(self.telemetry.position[2])
        return self.home_amsl

    def step(self, now: float) -> None:
        """Battery drain; home set again at arming."""
        armed = bool(self.commander.armed)
        if armed and not self._was_armed and self.telemetry is not None:
            self.set_home(self.telemetry.position)
        self._was_armed = armed
        self.battery.step(now, armed)

    # ------------------------------------------------------------------ messages
    def builders(self) -> dict[int, Callable[[float], Any | None]]:
        """Message id -> builder (None: nothing to report yet)."""
        return {
            M.MAVLINK_MSG_ID_HEARTBEAT: self.heartbeat,
            M.MAVLINK_MSG_ID_SYS_STATUS: self.sys_status,
            M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self.extended_sys_state,
            M.MAVLINK_MSG_ID_HOME_POSITION: self.home_position,
            M.MAVLINK_MSG_ID_GPS_RAW_INT: self.gps_raw_int,
            M.MAVLINK_MSG_ID_ATTITUDE: self.attitude,
            M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: self.attitude_quaternion,
            M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self.local_position_ned,
            M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self.global_position_int,
            M.MAVLINK_MSG_ID_VFR_HUD: self.vfr_hud,
            M.MAVLINK_MSG_ID_BATTERY_STATUS: self.battery_status,
        }

    def heartbeat_fields(self) -> tuple[int, int, int]:
        """(base_mode, custom_mode, system_status) as the heartbeat reports them."""
        cmd = self.commander
        mode = px4_mode_for_state(str(cmd.state))
        if cmd.failsafe:
            status = M.MAV_STATE_CRITICAL
        elif cmd.armed:
            status = M.MAV_STATE_ACTIVE
        else:
            status = M.MAV_STATE_STANDBY
        return base_mode_flags(cmd.armed, mode), mode.custom_mode, status

    def heartbeat(self, now: float = 0.0) -> Any:
        base, custom, status = self.heartbeat_fields()
        return M.MAVLink_heartbeat_message(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4, base,
                                           custom, status, 3)

    def sys_status(self, now: float = 0.0) -> Any:
        cmd, b = self.commander, self.battery
        health = _SENSORS
        if getattr(cmd, "failsafe_reason", None) == "geofence":
            health &= ~M.MAV_SYS_STATUS_GEOFENCE  # a breach (MAVProxy: "fence breach")
        if not cmd.failsafe and (cmd.armed or cmd.landed):
            health |= PREARM
        return M.MAVLink_sys_status_message(
            _SENSORS | PREARM, _SENSORS | PREARM, health, 0, int(round(b.voltage * 1000)),
            int(round(b.current_a * 100)), int(round(b.remaining * 100)), 0, 0, 0, 0, 0, 0,
            0, 0, 0)

    def extended_sys_state(self, now: float = 0.0) -> Any:
        return M.MAVLink_extended_sys_state_message(M.MAV_VTOL_STATE_UNDEFINED,
                                                    landed_state(self.commander))

    def battery_status(self, now: float = 0.0) -> Any:
        b = self.battery
        cell_mv = min(UINT16_MAX - 1, int(round(b.voltage / b.cells * 1000)))
        voltages = [cell_mv] * b.cells + [UINT16_MAX] * (10 - b.cells)
        time_left = int(b.remaining * b.capacity_mah / 1000.0 / b.current_a * 3600.0)
        return M.MAVLink_battery_status_message(
            0, M.MAV_BATTERY_FUNCTION_ALL, M.MAV_BATTERY_TYPE_LIPO, 32767, voltages,
            int(round(b.current_a * 100)), int(round(b.drawn_mah)), -1,
            int(round(b.remaining * 100)), time_left, b.charge_state, [0, 0, 0, 0],
            M.MAV_BATTERY_MODE_UNKNOWN, 0)

    def _geo(self, position: Vec3) -> tuple[int, int, int]:
        lat, lon, alt = frames.enu_to_geodetic(*position, self.origin)
        return int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000))

    def home_position(self, now: float = 0.0) -> Any | None:
        if self.home is None:
            return None
        lat, lon, alt = self._geo(self.home)
        x, y, z = frames.enu_to_ned(*self.home)
        usec = 0 if self.telemetry is None else int(round(self.telemetry.time * 1e6))
        return M.MAVLink_home_position_message(lat, lon, alt, x, y, z, [1.0, 0.0, 0.0, 0.0],
                                               0.0, 0.0, 0.0, usec)

    def gps_raw_int(self, now: float = 0.0) -> Any | None:
        t = self.telemetry
        if t is None:
            return None
        lat, lon, alt = self._geo(t.position)
        vn, ve, _ = frames.enu_to_ned(*t.velocity)
        speed = math.hypot(vn, ve)
        cog = _cdeg(math.atan2(ve, vn)) if speed > 0.05 else UINT16_MAX
        return M.MAVLink_gps_raw_int_message(
            int(round(t.time * 1e6)), M.GPS_FIX_TYPE_3D_FIX, lat, lon, alt, 80, 120,
            int(round(speed * 100)), cog, 10, alt, 500, 800, 200, 0, 0)

    def attitude(self, now: float = 0.0) -> Any | None:
        t = self.telemetry
        if t is None:
            return None
        roll, pitch, yaw = frames.euler_enu_to_ned(*t.attitude)
        p, q, r = frames.body_rates_flu_to_frd(*t.body_rates)
        return M.MAVLink_attitude_message(_ms(t), roll, pitch, yaw, p, q, r)

    def attitude_quaternion(self, now: float = 0.0) -> Any | None:
        t = self.telemetry
        if t is None:
            return None
        q = frames.quat_from_euler(*frames.euler_enu_to_ned(*t.attitude))
        p, qq, r = frames.body_rates_flu_to_frd(*t.body_rates)
        return M.MAVLink_attitude_quaternion_message(_ms(t), *q, p, qq, r, [0.0] * 4)

    def local_position_ned(self, now: float = 0.0) -> Any | None:
        t = self.telemetry
        if t is None:
            return None
        x, y, z = frames.enu_to_ned(*t.position)
        vx, vy, vz = frames.enu_to_ned(*t.velocity)
        return M.MAVLink_local_position_ned_message(_ms(t), x, y, z, vx, vy, vz)

    def global_position_int(self, now: float = 0.0) -> Any | None:
        t = self.telemetry
        if t is None:
            return None
        lat, lon, alt = self._geo(t.position)
        home_up = 0.0 if self.home is None else self.home[2]
        vx, vy, vz = frames.enu_to_ned(*t.velocity)
        yaw = frames.yaw_enu_to_ned(t.attitude[2])
        return M.MAVLink_global_position_int_message(
            _ms(t), lat, lon, alt, int(round((t.position[2] - home_up) * 1000)),
            int(round(vx * 100)), int(round(vy * 100)), int(round(vz * 100)), _cdeg(yaw))

    def vfr_hud(self, now: float = 0.0) -> Any | None:
        t = self.telemetry
        if t is None:
            return None
        speed = math.hypot(t.velocity[0], t.velocity[1])
        heading = _cdeg(frames.yaw_enu_to_ned(t.attitude[2])) // 100
        throttle = 50 if self.commander.armed else 0
        return M.MAVLink_vfr_hud_message(speed, speed, heading, throttle,
                                         self.origin[2] + t.position[2], t.velocity[2])


def _ms(t: VehicleTelemetry) -> int:
    return int(round(t.time * 1000.0)) & 0xFFFFFFFF
