"""The companion-computer side of MAVLink: an offboard client, as MAVSDK's Action+Offboard.

It sits where a MAVSDK offboard client sits in PX4 SITL: it listens on UDP 14540 (the
vehicle's API link sends there from its own port), learns the vehicle's address from
the autopilot's heartbeat (system ``target_system``, component 1, autopilot not
INVALID) and answers to it.

Setpoints are given in skyloop's frames (:class:`~mavlink_bridge.interfaces.
VelocityCommand`: world ENU, or body-horizontal FLU) and converted once through
:mod:`mavlink_bridge.frames`; they go out as SET_POSITION_TARGET_LOCAL_NED with the
velocity + yaw-rate type mask 0x05C7 in MAV_FRAME_LOCAL_NED or MAV_FRAME_BODY_NED. The
wire carries float32: the vehicle sees ``float32(value)`` (the ENU<->NED swaps and sign
flips are exact, so rounding an action to float32 reproduces what arrives).

Driving it: :meth:`OffboardClient.poll` is non-blocking (drain the socket, track the
vehicle's heartbeat/acks/telemetry, re-send the latest setpoint every
``setpoint_period`` while streaming -- MAVSDK does that at 20 Hz from a thread -- and send
our own heartbeat). With ``security.secret_key`` set (the vehicle's key) everything it sends
is signed and only signed vehicle traffic is believed (:mod:`mavlink_bridge.security`).
The actions (:meth:`~OffboardClient.arm`, :meth:`~OffboardClient.
takeoff`, :meth:`~OffboardClient.start_offboard`, :meth:`~OffboardClient.land`, ...) block
until the vehicle's COMMAND_ACK (retrying like MAVSDK) and raise :class:`CommandRejected`
or :class:`CommandTimeout`. While they wait they poll and, between polls, call ``spin()``
if one was given (a test or a lockstep loop advances the simulated vehicle there, with
``clock`` reading the same simulated time) or else sleep in ``select`` on the socket.
"""

from __future__ import annotations

import math
import select
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from mavlink_bridge import frames
from mavlink_bridge.interfaces import VelocityCommand
from mavlink_bridge.modes import AUTO_LOITER, OFFBOARD, BaseMode, Px4Mode, is_armed
from mavlink_bridge.security import LinkSecurity
from mavlink_bridge.transport import Address, UdpEndpoint, mavlink
from mavlink_bridge.validate import MASK_VELOCITY_YAW_RATE, MAV_FRAME_BODY_NED, MAV_FRAME_LOCAL_NED


class OffboardError(RuntimeError):
    """An offboard client action failed."""


class CommandTimeout(OffboardError):
    """No COMMAND_ACK arrived in time."""


class CommandRejected(OffboardError):
    """The vehicle answered with a result other than ACCEPTED."""

    def __init__(self, command: int, result: int) -> None:
        super().__init__(f"command {command} rejected with MAV_RESULT {result}")
        self.command = command
        self.result = result


@dataclass
class OffboardClientConfig:
    """Where to listen, who we are, whom we fly, and timing (s)."""

    listen_host: str = "127.0.0.1"
    listen_port: int = 14540
    system_id: int = 245  # MAVSDK's default ground-station ids
    component_id: int = 190
    target_system: int = 1  # 0: the first autopilot heard
    target_component: int = 1
    command_timeout: float = 0.5  # per attempt (MAVSDK: 0.5 s)
    command_attempts: int = 3
    setpoint_period: float = 0.05  # re-send while streaming (MAVSDK: 20 Hz)
    prestream: float = 0.2  # stream this long before asking for OFFBOARD
    mode_timeout: float = 3.0  # heartbeat must show OFFBOARD within this (MAVSDK: 3 s)
    heartbeat_period: float = 1.0
    link_timeout: float = 3.0  # no vehicle heartbeat this long: disconnected
    security: LinkSecurity | None = None  # signing key (as the vehicle's), --expose


class OffboardClient:
    """A MAVLink offboard client over UDP (see the module docstring)."""

    def __init__(self, config: OffboardClientConfig | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 spin: Callable[[], None] | None = None) -> None:
        self.config = c = config or OffboardClientConfig()
        self.clock = clock
        self.spin = spin
        self.endpoint = UdpEndpoint((c.listen_host, c.listen_port), None, c.system_id,
                                    c.component_id, name="offboard", follow_sender=False,
                                    security=c.security)
        self.vehicle: Address | None = None
        self.vehicle_system = c.target_system
        self.mode: Px4Mode | None = None
        self.armed = False
        self.system_status = 0
        self.last_heartbeat = -math.inf
        self.local_position: Any = None  # latest LOCAL_POSITION_NED
        self.attitude: Any = None  # latest ATTITUDE
        self.statustexts: deque[tuple[int, str]] = deque(maxlen=100)
        self._acks: dict[int, int] = {}
        #: (MAV frame, NED fields, time_boot_ms or None: the client's clock)
        self._setpoint: tuple[int, tuple[float, float, float, float], int | None] | None = None
        self._next_setpoint = math.inf
        self._next_heartbeat = -math.inf
        self._t0 = clock()

    @property
    def address(self) -> Address:
        """Where we listen (the vehicle's API link must send here)."""
        return self.endpoint.address

    @property
    def connected(self) -> bool:
        return self.clock() - self.last_heartbeat <= self.config.link_timeout

    # ------------------------------------------------------------------ loop
    def poll(self) -> int:
        """Drain and handle incoming messages, send what is due; messages handled."""
        msgs = self.endpoint.receive()
        for msg, addr in msgs:
            self._handle(msg, addr)
        now = self.clock()
        if self.vehicle is not None:
            if self._setpoint is not None and now >= self._next_setpoint:
                due = self._next_setpoint
                self._send_setpoint()
                if now - due < self.config.setpoint_period:  # keep the rate, no drift
                    self._next_setpoint = due + self.config.setpoint_period
            if now >= self._next_heartbeat:
                self._next_heartbeat = now + self.config.heartbeat_period
                self.endpoint.send(mavlink.MAVLink_heartbeat_message(
                    mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                    mavlink.MAV_STATE_ACTIVE, 3))
        return len(msgs)

    def _handle(self, msg: Any, addr: Address) -> None:
        c = self.config
        kind = msg.get_type()
        src, comp = msg.get_srcSystem(), msg.get_srcComponent()
        if kind == "HEARTBEAT":
            if comp != c.target_component or msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID:
                return
            if self.vehicle_system == 0:
                self.vehicle_system = src
            if src != self.vehicle_system:
                return
            self.vehicle = self.endpoint.peer = addr
            self.last_heartbeat = self.clock()
            self.mode = Px4Mode.from_custom_mode(msg.custom_mode)
            self.armed = is_armed(msg.base_mode)
            self.system_status = msg.system_status
            return
        if src != self.vehicle_system:
            return
        if kind == "COMMAND_ACK":
            if msg.target_system in (0, c.system_id):
                self._acks[msg.command] = msg.result
        elif kind == "LOCAL_POSITION_NED":
            self.local_position = msg
        elif kind == "ATTITUDE":
            self.attitude = msg
        elif kind == "STATUSTEXT":
            self.statustexts.append((msg.severity, msg.text))

    def wait(self, condition: Callable[[], bool], timeout: float) -> bool:
        """Poll (and spin) until ``condition()`` or ``timeout`` s on ``clock``."""
        deadline = self.clock() + timeout
        while True:
            self.poll()
            if condition():
                return True
            now = self.clock()
            if now >= deadline:
                return False
            if self.spin is not None:
                self.spin()
            else:
                select.select([self.endpoint.fileno()], [], [],
                              min(deadline - now, self.config.setpoint_period))

    def wait_heartbeat(self, timeout: float = 3.0) -> None:
        """Block until the vehicle's heartbeat has been heard (its address learnt)."""
        if not self.wait(lambda: self.vehicle is not None, timeout):
            raise OffboardError(f"no heartbeat from system {self.vehicle_system} "
                                f"within {timeout:g} s")

    # ------------------------------------------------------------------ setpoints
    def send_velocity(self, command: VelocityCommand, time_boot_ms: int | None = None) -> None:
        """Send a velocity + yaw-rate setpoint now and keep streaming it.
        ``command.yaw`` is not sent (the mask carries the yaw rate). ``time_boot_ms``
        stamps the setpoint and its re-sends (a lockstep companion stamps the step it
        answers: the stack time in ms); None: the client's clock since it started."""
        if command.frame_is_body:
            frame, fields = MAV_FRAME_BODY_NED, frames.velocity_flu_to_body_ned(
                command.vx, command.vy, command.vz, command.yaw_rate)
        else:
            frame, fields = MAV_FRAME_LOCAL_NED, frames.velocity_enu_to_local_ned(
                command.vx, command.vy, command.vz, command.yaw_rate)
        self._setpoint = (frame, fields, time_boot_ms)
        if self.vehicle is not None:
            self._send_setpoint()
        else:
            self._next_setpoint = -math.inf  # first poll after the heartbeat sends it

    def set_velocity_body(self, forward: float, left: float, up: float,
                          yaw_rate: float, time_boot_ms: int | None = None) -> None:
        """Body-horizontal FLU velocity (m/s) and CCW yaw rate (rad/s), streamed."""
        self.send_velocity(VelocityCommand(forward, left, up, yaw_rate, True), time_boot_ms)

    def set_velocity_enu(self, east: float, north: float, up: float, yaw_rate: float,
                         time_boot_ms: int | None = None) -> None:
        """World ENU velocity (m/s) and CCW yaw rate (rad/s), streamed."""
        self.send_velocity(VelocityCommand(east, north, up, yaw_rate, False), time_boot_ms)

    def resend(self) -> None:
        """Send the current setpoint again now (same stamp), if there is one."""
        if self._setpoint is not None and self.vehicle is not None:
            self._send_setpoint()

    def set_stream_period(self, period: float) -> None:
        """Re-send the current setpoint every ``period`` s from now on (``math.inf``:
        only when told, by a new setpoint or :meth:`resend`)."""
        self.config.setpoint_period = period
        self._next_setpoint = self.clock() + period

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        """Send a STATUSTEXT (first 50 bytes) to the vehicle, which shows it to ground
        stations as a companion's message."""
        if self.vehicle is None:
            raise OffboardError("vehicle not connected (no heartbeat yet)")
        raw = text.encode("utf-8", "replace")[:50]
        self.endpoint.send(mavlink.MAVLink_statustext_message(severity, raw, 0, 0))

    def stop_stream(self) -> None:
        """Stop re-sending setpoints (the vehicle's setpoint-loss failsafe will act)."""
        self._setpoint = None

    def _send_setpoint(self) -> None:
        assert self._setpoint is not None
        frame, (vx, vy, vz, yaw_rate), stamp = self._setpoint
        ms = (int((self.clock() - self._t0) * 1000.0) if stamp is None else stamp) & 0xFFFFFFFF
        self.endpoint.send(mavlink.MAVLink_set_position_target_local_ned_message(
            ms, self.vehicle_system, self.config.target_component, frame,
            MASK_VELOCITY_YAW_RATE, 0.0, 0.0, 0.0, vx, vy, vz, 0.0, 0.0, 0.0, 0.0, yaw_rate))
        self._next_setpoint = self.clock() + self.config.setpoint_period

    # ------------------------------------------------------------------ commands
    def command(self, command: int, *params: float) -> int:
        """Send COMMAND_LONG (up to 7 params, the rest 0) and return the MAV_RESULT,
        retrying ``command_attempts`` times; :class:`CommandTimeout` if never answered."""
        if self.vehicle is None:
            raise OffboardError("vehicle not connected (no heartbeat yet)")
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        c = self.config
        in_progress = mavlink.MAV_RESULT_IN_PROGRESS
        for attempt in range(c.command_attempts):
            self.poll()  # take in any stale ACK for this command before forgetting it
            self._acks.pop(command, None)
            self.endpoint.send(mavlink.MAVLink_command_long_message(
                self.vehicle_system, c.target_component, command, attempt, *p))
            if self.wait(lambda: self._acks.get(command, in_progress) != in_progress,
                         c.command_timeout):
                return self._acks[command]
        raise CommandTimeout(f"no COMMAND_ACK for command {command} after "
                             f"{c.command_attempts} attempts")

    def _expect_accepted(self, command: int, *params: float) -> None:
        result = self.command(command, *params)
        if result != mavlink.MAV_RESULT_ACCEPTED:
            raise CommandRejected(command, result)

    def arm(self) -> None:
        self._expect_accepted(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)

    def disarm(self, force: bool = False) -> None:
        self._expect_accepted(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0,
                              21196.0 if force else 0.0)

    def takeoff(self, altitude: float | None = None) -> None:
        """Take off to ``altitude`` m above the takeoff point (None: the vehicle's default,
        MIS_TAKEOFF_ALT). skyloop reads a param7 at or below home's AMSL altitude as
        relative (``vehicle_link.takeoff_altitude``); PX4 would read it as AMSL."""
        alt = math.nan if altitude is None else altitude
        self._expect_accepted(mavlink.MAV_CMD_NAV_TAKEOFF, 0.0, 0.0, 0.0, math.nan,
                              math.nan, math.nan, alt)

    def land(self) -> None:
        self._expect_accepted(mavlink.MAV_CMD_NAV_LAND, 0.0, 0.0, 0.0, math.nan,
                              math.nan, math.nan, math.nan)

    def set_mode(self, mode: Px4Mode) -> None:
        """DO_SET_MODE to a PX4 mode (ack only; see :meth:`start_offboard` for the check)."""
        self._expect_accepted(mavlink.MAV_CMD_DO_SET_MODE, float(BaseMode.CUSTOM_MODE_ENABLED),
                              float(mode.main), float(mode.sub))

    def hold(self) -> None:
        self.set_mode(AUTO_LOITER)

    def start_offboard(self) -> None:
        """Stream the current setpoint for ``prestream`` s, switch to OFFBOARD, and wait
        until the heartbeat shows main mode 6. A setpoint must have been set first."""
        if self._setpoint is None:
            raise OffboardError("set a setpoint before starting offboard")
        self.wait(lambda: False, self.config.prestream)
        self.set_mode(OFFBOARD)
        if not self.wait(lambda: self.mode == OFFBOARD, self.config.mode_timeout):
            raise OffboardError(f"heartbeat did not show OFFBOARD within "
                                f"{self.config.mode_timeout} s")

    def stop_offboard(self) -> None:
        """Switch to Hold and stop streaming (MAVSDK's ``offboard.stop``)."""
        self.hold()
        self.stop_stream()

    def close(self) -> None:
        self.endpoint.close()

    def __enter__(self) -> OffboardClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
