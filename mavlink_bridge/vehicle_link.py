"""The vehicle's MAVLink endpoint, PX4 SITL style: an API link and a GCS link over UDP.

System 1, component 1 (autopilot), MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, MAVLink 2.
Two links, as PX4 SITL has them (all addresses configurable, loopback by default):

* **api**: sends to UDP 14540 (where an offboard client such as MAVSDK or skyloop's
  policy listens) from local port 14580;
* **gcs**: sends to UDP 14550 (QGroundControl, MAVProxy) from local port 18570.

Each link answers on its own socket to whoever spoke last (PX4's partner following);
until someone speaks, it sends to its configured remote.

Driving it: :meth:`VehicleLink.poll` is non-blocking and does all the work for one
instant ``now`` (seconds on the vehicle's clock, simulated or wall): drain both sockets,
handle every message, then send what is due on each link (heartbeat every
``heartbeat_period`` and at once when the reported mode/arming/status changes;
LOCAL_POSITION_NED + ATTITUDE every ``telemetry_period`` and the rest of the PX4-like
telemetry set at the rates of :mod:`mavlink_bridge.gcs.rates`, from the latest
:class:`VehicleTelemetry` and the commander). No threads and no clock
reads, so a lockstep simulator calls it once per control step and gets the same
behaviour every run; a real-time node calls it from its loop (or after ``select`` on
:meth:`VehicleLink.fileno` values).

Handled: COMMAND_LONG ARM_DISARM (400; param2 21196 forces a disarm), NAV_TAKEOFF (22;
param7 read by :func:`takeoff_altitude` against the takeoff point's AMSL altitude,
``TelemetryReporter.takeoff_amsl``: NaN -> the vehicle's default, MIS_TAKEOFF_ALT; above
it -> AMSL, as PX4 and QGroundControl; at or below it -> metres above the takeoff point,
skyloop's extension for MAVProxy's ``takeoff 3``; accepted disarmed too, as PX4: the
vehicle reports AUTO.TAKEOFF and climbs once armed, QGroundControl's Takeoff), NAV_LAND (21),
NAV_RETURN_TO_LAUNCH (20, i.e. mode RTL), DO_SET_MODE (176, PX4 custom modes), each
answered by COMMAND_ACK carrying the commander's verdict; other commands are answered
UNSUPPORTED. The SET_MODE message (11; QGroundControl's route for every PX4 mode change:
its mode menu, Hold, Land, RTL) asks the same as DO_SET_MODE with ``custom_mode`` the
whole PX4 value; it has no acknowledgement (the heartbeat and the commander's
STATUSTEXT show the outcome), counted ``set_mode.<MAV_RESULT>``; its armed bit is ignored.
SET_POSITION_TARGET_LOCAL_NED is validated (:mod:`mavlink_bridge.validate`) and
delivered to ``on_setpoint(command, now, time_boot_ms)`` (the stamp: the step it answers).
Every refusal and every bad frame is counted
(:attr:`VehicleLink.counters`); nothing received can raise out of :meth:`poll`.
Commander events reach ground stations through :meth:`VehicleLink.statustext`; a
STATUSTEXT received on one link (the companion's) is forwarded on the others.
Further messages and commands plug in through :attr:`VehicleLink.handlers` (message type
-> handler) and :attr:`VehicleLink.commands` (command id -> MAV_RESULT function); a
command handler may queue a message to follow its COMMAND_ACK
(:meth:`VehicleLink.reply_after_ack`). COMMAND_INT is handled as COMMAND_LONG.

What ground stations expect on connect (issue 5) is installed by
:mod:`mavlink_bridge.gcs.services`: REQUEST_MESSAGE / AUTOPILOT_VERSION, parameters
(:attr:`VehicleLink.params`, ``on_change``), missions (:attr:`VehicleLink.missions`,
``on_mission``, ``mission_current``, ``item_reached``), telemetry streams and their rates
(:attr:`VehicleLink.rates`, SET/GET_MESSAGE_INTERVAL), TIMESYNC. The geodetic origin of
the local frame is ``VehicleLinkConfig.origin``; home is the first position, then the
position at arming (:meth:`VehicleLink.set_home` overrides).
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from mavlink_bridge.gcs.services import GroundStationServices
from mavlink_bridge.interfaces import CommanderLike, VehicleTelemetry, VelocityCommand, Verdict
from mavlink_bridge.modes import (
    BaseMode,
    Px4Mode,
    state_for_px4_mode,
)
from mavlink_bridge.security import LinkSecurity
from mavlink_bridge.transport import Address, UdpEndpoint, mavlink
from mavlink_bridge.validate import SetpointLimits, SetpointValidator

log = logging.getLogger(__name__)

FORCE_DISARM_MAGIC = 21196.0
SEVERITY = {"emergency": 0, "alert": 1, "critical": 2, "error": 3, "warning": 4,
            "notice": 5, "info": 6, "debug": 7}
_TEMPORARY = {"no_setpoint_stream", "busy"}
_UNSUPPORTED = {"unsupported_mode", "unsupported"}


@dataclass
class LinkConfig:
    """One UDP link: bound to ``local``, sending to ``remote`` until someone speaks."""

    local_port: int
    remote_port: int
    local_host: str = "127.0.0.1"
    remote_host: str = "127.0.0.1"


@dataclass
class VehicleLinkConfig:
    """The vehicle's MAVLink identity, links and rates (``gcs``/``api`` None: off)."""

    system_id: int = 1
    component_id: int = 1
    api: LinkConfig | None = field(default_factory=lambda: LinkConfig(14580, 14540))
    gcs: LinkConfig | None = field(default_factory=lambda: LinkConfig(18570, 14550))
    heartbeat_period: float = 1.0  # s
    telemetry_period: float = 0.1  # s, LOCAL_POSITION_NED and ATTITUDE
    limits: SetpointLimits = field(default_factory=SetpointLimits)
    # Ground-station protocol (issue 5): the geodetic point of the local ENU origin
    # (lat deg, lon deg, alt m AMSL; PX4 SITL's default), and the parameter file
    # ("auto": mavlink_bridge.gcs.params.default_params_file(system_id); None: memory only).
    origin: tuple[float, float, float] = (47.397742, 8.545594, 488.0)
    params_file: str | None = "auto"
    security: LinkSecurity | None = None  # signing, allow-list, --expose (both links)

    @classmethod
    def for_instance(cls, instance: int, **kwargs: Any) -> VehicleLinkConfig:
        """PX4 SITL's multi-vehicle numbering: vehicle ``i`` is system ``1 + i``, its API
        link 14580 + i -> 14540 + i, its GCS link 18570 + i -> 14550."""
        return cls(system_id=1 + instance, api=LinkConfig(14580 + instance, 14540 + instance),
                   gcs=LinkConfig(18570 + instance, 14550), **kwargs)


def mav_result(verdict: Verdict) -> int:
    """MAV_RESULT for a commander verdict (see :mod:`mavlink_bridge.interfaces`)."""
    if verdict.accepted:
        return mavlink.MAV_RESULT_ACCEPTED
    if verdict.reason in _TEMPORARY:
        return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    if verdict.reason in _UNSUPPORTED:
        return mavlink.MAV_RESULT_UNSUPPORTED
    return mavlink.MAV_RESULT_DENIED


def takeoff_altitude(param7: float, reference_amsl: float) -> float | None:
    """NAV_TAKEOFF's param7 as metres to climb above the takeoff point (None: the
    vehicle's default, MIS_TAKEOFF_ALT), given the takeoff point's altitude AMSL (m;
    ``TelemetryReporter.takeoff_amsl``: where the vehicle stands, else home).

    * NaN: None (MAVSDK's ``action.takeoff()`` sends NaN and sets MIS_TAKEOFF_ALT with
      ``set_takeoff_altitude``; PX4 then climbs MIS_TAKEOFF_ALT above home);
    * above ``reference_amsl``: an AMSL altitude, as PX4 reads it (QGroundControl sends
      the vehicle's AMSL altitude + the relative one): ``param7 - reference_amsl``;
    * at or below it: already metres above the takeoff point (skyloop's extension, so
      MAVProxy's ``takeoff 3`` and ``OffboardClient.takeoff(3)`` work; a relative
      altitude above the AMSL altitude would be read as AMSL).

    Nothing is checked here: the commander refuses what it cannot fly (``bad_altitude``).
    """
    if math.isnan(param7):
        return None
    return param7 - reference_amsl if param7 > reference_amsl else param7


def _byte_param(value: float) -> int | None:
    """A command parameter that must be a whole number 0..255, else None."""
    if not math.isfinite(value) or value != int(value) or not 0 <= value <= 255:
        return None
    return int(value)


class VehicleLink:
    """The vehicle side of MAVLink: heartbeat, telemetry, commands, setpoints."""

    def __init__(self, commander: CommanderLike, config: VehicleLinkConfig | None = None,
                 on_setpoint: Callable[[VelocityCommand, float, int], None] | None = None,
                 ) -> None:
        self.config = c = config or VehicleLinkConfig()
        self.commander = commander
        self.on_setpoint = on_setpoint
        self.validator = SetpointValidator(c.system_id, c.component_id, c.limits)
        self.received: Counter[str] = Counter()  # good messages by type
        self._counters: Counter[str] = Counter()  # command/handler outcomes
        self.endpoints: dict[str, UdpEndpoint] = {}
        try:
            for name, lc in (("api", c.api), ("gcs", c.gcs)):
                if lc is not None:
                    self.endpoints[name] = UdpEndpoint(
                        (lc.local_host, lc.local_port), (lc.remote_host, lc.remote_port),
                        c.system_id, c.component_id, name=name, security=c.security)
        except (OSError, ValueError):
            self.close()
            raise
        # Extension points (parameters, missions, REQUEST_MESSAGE, ... of issue 5):
        # a handler per message type, and one per COMMAND_LONG id returning a MAV_RESULT.
        self.handlers: dict[str, Callable[[UdpEndpoint, Any, Address, float], None]] = {
            "SET_POSITION_TARGET_LOCAL_NED": self._on_setpoint_msg,
            "COMMAND_LONG": self._on_command_long,
            "COMMAND_INT": self._on_command_int,
            "SET_MODE": self._on_set_mode,
            "STATUSTEXT": self._on_statustext,
        }
        self.commands: dict[int, Callable[[Any, float], int]] = {
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM: self._cmd_arm_disarm,
            mavlink.MAV_CMD_NAV_TAKEOFF: self._cmd_takeoff,
            mavlink.MAV_CMD_NAV_LAND: lambda msg, now: mav_result(self.commander.land(now)),
            mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
                lambda msg, now: mav_result(self.commander.set_mode(now, "RTL")),
            mavlink.MAV_CMD_DO_SET_MODE: self._cmd_set_mode,
        }
        self._after_ack: list[Any] = []  # sent to a command's sender after its ACK
        self.command_link: UdpEndpoint | None = None  # the link the current command came on
        # Ground-station protocol (issue 5): parameters, missions, streams, requests.
        self.services = GroundStationServices(self)
        self.services.install()
        self.params = self.services.params
        self.missions = self.services.missions
        self.reporter = self.services.reporter
        self.rates = self.services.rates
        self.messages = self.services.messages

    # ------------------------------------------------------------------ public
    def address(self, name: str) -> Address:
        """The bound local address of link ``"api"`` or ``"gcs"``."""
        return self.endpoints[name].address

    @property
    def counters(self) -> Counter[str]:
        """Everything counted so far: per-link frame counters (``api.rx_bad_crc``, ...),
        setpoint refusals (``setpoint.nan``, ...), command outcomes (``cmd.<id>.<MAV_RESULT>``
        for handled ids, ``cmd.unsupported``, ``cmd.other_target``), ``handler_error``."""
        out: Counter[str] = Counter(self._counters)
        for name, ep in self.endpoints.items():
            out.update({f"{name}.{k}": v for k, v in ep.counters.items()})
        out.update({f"setpoint.{k.value}": v for k, v in self.validator.rejected.items()})
        out["setpoint.accepted"] = self.validator.accepted
        out.update(self.services.all_counters())
        return out

    def broadcast(self, msg: Any) -> None:
        """Send ``msg`` on every link (to each link's current peer)."""
        self._broadcast(msg)

    def update_telemetry(self, telemetry: VehicleTelemetry) -> None:
        """The vehicle state to report from now on (ENU/FLU, see the dataclass)."""
        self.reporter.update(telemetry)

    def set_home(self, position: tuple[float, float, float]) -> None:
        """Home (local ENU) from now on (default: first position, then each arming)."""
        self.reporter.set_home(position)

    def statustext(self, text: str, severity: str | int = "info") -> None:
        """Send a STATUSTEXT (truncated to 50 bytes) on every link."""
        sev = severity if isinstance(severity, int) else SEVERITY.get(severity, 6)
        raw = text.encode("utf-8", "replace")[:50]
        self._broadcast(mavlink.MAVLink_statustext_message(sev, raw, 0, 0))

    def poll(self, now: float) -> int:
        """Handle everything waiting, then send what is due at ``now``; messages handled."""
        handled = 0
        for ep in self.endpoints.values():
            for msg, addr in ep.receive():
                handled += 1
                try:
                    self._handle(ep, msg, addr, now)
                except Exception:  # a bug or odd input must not take the vehicle down
                    self._counters["handler_error"] += 1
                    if self._counters["handler_error"] & (self._counters["handler_error"] - 1) == 0:
                        log.exception("error handling %s from %s", msg.get_type(), addr)
        self.services.poll(now)  # mission upload retries, then every stream due
        return handled

    def fileno(self) -> list[int]:
        """Socket descriptors, for ``select`` in a real-time loop."""
        return [ep.fileno() for ep in self.endpoints.values()]

    def close(self) -> None:
        for ep in self.endpoints.values():
            ep.close()

    def __enter__(self) -> VehicleLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ outgoing
    def _broadcast(self, msg: Any) -> None:
        for ep in self.endpoints.values():
            ep.send(msg)

    # ------------------------------------------------------------------ incoming
    def _handle(self, ep: UdpEndpoint, msg: Any, addr: Address, now: float) -> None:
        kind = msg.get_type()
        self.received[kind] += 1
        handler = self.handlers.get(kind)
        if handler is not None:
            handler(ep, msg, addr, now)

    def _on_setpoint_msg(self, ep: UdpEndpoint, msg: Any, addr: Address, now: float) -> None:
        result = self.validator.validate(msg)
        if isinstance(result, VelocityCommand) and self.on_setpoint is not None:
            self.on_setpoint(result, now, int(msg.time_boot_ms))

    def _on_statustext(self, ep: UdpEndpoint, msg: Any, addr: Address, now: float) -> None:
        """A STATUSTEXT from a link (the companion's policy node) goes on to the other
        links as the vehicle's, as PX4 forwards its companion's (counted)."""
        text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("utf-8",
                                                                                "replace")
        raw = text.rstrip("\x00").encode("utf-8", "replace")[:50]
        out = mavlink.MAVLink_statustext_message(int(msg.severity), raw, 0, 0)
        for other in self.endpoints.values():
            if other is not ep:
                other.send(out)
        self._counters["statustext.forwarded"] += 1

    def _on_command_long(self, ep: UdpEndpoint, msg: Any, addr: Address, now: float) -> None:
        c = self.config
        if msg.target_system != c.system_id or msg.target_component not in (0, c.component_id):
            self._counters["cmd.other_target"] += 1
            return
        handler = self.commands.get(msg.command)
        self._after_ack.clear()
        self.command_link = ep
        if handler is None:  # one counter for all unknown ids: the key set stays bounded
            result = mavlink.MAV_RESULT_UNSUPPORTED
            self._counters["cmd.unsupported"] += 1
        else:
            result = handler(msg, now)
            self._counters[f"cmd.{msg.command}.{result}"] += 1
        ep.send(mavlink.MAVLink_command_ack_message(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()), addr)
        if result == mavlink.MAV_RESULT_ACCEPTED:
            for reply in self._after_ack:  # e.g. the message REQUEST_MESSAGE asked for
                ep.send(reply, addr)
            self.services.send_due(now)  # the heartbeat shows a new mode/arming at once
        self._after_ack.clear()

    def _on_command_int(self, ep: UdpEndpoint, msg: Any, addr: Address, now: float) -> None:
        """COMMAND_INT as COMMAND_LONG: param5/6 are the integer x/y, param7 is z."""
        self._on_command_long(ep, _CommandIntAsLong(msg), addr, now)

    def reply_after_ack(self, msg: Any) -> int:
        """For a command handler: send ``msg`` to the sender after the ACK; ACCEPTED."""
        self._after_ack.append(msg)
        return mavlink.MAV_RESULT_ACCEPTED

    def _cmd_arm_disarm(self, msg: Any, now: float) -> int:
        if msg.param1 == 1.0:
            return mav_result(self.commander.arm(now))
        if msg.param1 == 0.0:
            return mav_result(self.commander.disarm(now, force=msg.param2 == FORCE_DISARM_MAGIC))
        return mavlink.MAV_RESULT_DENIED

    def _cmd_takeoff(self, msg: Any, now: float) -> int:
        altitude = takeoff_altitude(float(msg.param7), self.reporter.takeoff_amsl)
        return mav_result(self.commander.takeoff(now, altitude))

    def _cmd_set_mode(self, msg: Any, now: float) -> int:
        base = _byte_param(msg.param1)
        main, sub = _byte_param(msg.param2), _byte_param(msg.param3)
        if base is None or main is None or sub is None:
            return mavlink.MAV_RESULT_DENIED
        return self._set_mode(base, Px4Mode(main, sub), now)

    def _set_mode(self, base: int, mode: Px4Mode, now: float) -> int:
        if not base & BaseMode.CUSTOM_MODE_ENABLED:
            return mavlink.MAV_RESULT_UNSUPPORTED
        state = state_for_px4_mode(mode)
        if state is None:
            return mavlink.MAV_RESULT_UNSUPPORTED
        return mav_result(self.commander.set_mode(now, state))

    def _on_set_mode(self, ep: UdpEndpoint, msg: Any, addr: Address, now: float) -> None:
        if msg.target_system != self.config.system_id:
            self._counters["set_mode.other_target"] += 1
            return
        result = self._set_mode(msg.base_mode, Px4Mode.from_custom_mode(msg.custom_mode), now)
        self._counters[f"set_mode.{result}"] += 1
        if result == mavlink.MAV_RESULT_ACCEPTED:
            self.services.send_due(now)  # the heartbeat shows the new mode at once


class _CommandIntAsLong:
    """A COMMAND_INT seen through COMMAND_LONG's field names (param5/6 = x/y as sent)."""

    def __init__(self, msg: Any) -> None:
        self._msg = msg
        self.command, self.target_system = msg.command, msg.target_system
        self.target_component = msg.target_component
        self.param1, self.param2, self.param3, self.param4 = (
            msg.param1, msg.param2, msg.param3, msg.param4)
        self.param5, self.param6, self.param7 = float(msg.x), float(msg.y), msg.z
        self.frame = msg.frame

    def get_srcSystem(self) -> int:  # noqa: N802 (pymavlink's name)
        return int(self._msg.get_srcSystem())

    def get_srcComponent(self) -> int:  # noqa: N802
        return int(self._msg.get_srcComponent())
