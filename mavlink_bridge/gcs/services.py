"""What ground stations expect on connect, plugged into a :class:`VehicleLink` (issue 5).

:func:`install` adds to a link's ``handlers``/``commands`` tables and returns the
:class:`GroundStationServices` that own the state behind them:

* ``messages`` -- message id -> builder, for MAV_CMD_REQUEST_MESSAGE (512; COMMAND_ACK,
  then the message to the requester) and for the streams: AUTOPILOT_VERSION (also on
  the legacy MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 520), MISSION_CURRENT and every
  telemetry message of :mod:`mavlink_bridge.gcs.telemetry`;
* ``rates`` -- one :class:`~mavlink_bridge.gcs.rates.MessageRates` per link;
  MAV_CMD_SET_MESSAGE_INTERVAL (511) / GET_MESSAGE_INTERVAL (510) act on the link the
  command came in on;
* ``params`` (:mod:`mavlink_bridge.gcs.params`) and ``missions``
  (:mod:`mavlink_bridge.gcs.missions`): their messages are answered to the sender, messages
  addressed to another system are counted (``<message>.other_target``) and ignored;
* TIMESYNC: a request (tc1 == 0) is answered with tc1 = the vehicle's ``now`` in ns
  and ts1 echoed;
* FILE_TRANSFER_PROTOCOL: refused at once (:mod:`mavlink_bridge.gcs.ftp`), so a ground
  station that tries MAVLink FTP first falls back to the parameter protocol;
* :meth:`GroundStationServices.send_due` -- the heartbeat at once on a
  mode/arming/status change, HOME_POSITION at once when home moves, every stream when due.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from mavlink_bridge.gcs.autopilot_version import autopilot_version
from mavlink_bridge.gcs.ftp import FtpRefuser
from mavlink_bridge.gcs.missions import MissionServer
from mavlink_bridge.gcs.params import ParamServer, default_params_file
from mavlink_bridge.gcs.rates import MessageRates, default_intervals
from mavlink_bridge.gcs.telemetry import TelemetryReporter
from mavlink_bridge.transport import Address, UdpEndpoint, mavlink

if TYPE_CHECKING:
    from mavlink_bridge.vehicle_link import VehicleLink

M = mavlink


class GroundStationServices:
    """Parameters, missions, telemetry streams and message requests of one vehicle."""

    def __init__(self, link: VehicleLink) -> None:
        self.link = link
        c = link.config
        self.counters: Counter[str] = Counter()
        params_file = default_params_file(c.system_id) if c.params_file == "auto" \
            else c.params_file
        self.params = ParamServer(link, params_file)
        self.missions = MissionServer(link)
        self.ftp = FtpRefuser(c.system_id, c.component_id)
        self.reporter = TelemetryReporter(link.commander, c.origin)
        self.messages: dict[int, Callable[[float], Any | None]] = {
            M.MAVLINK_MSG_ID_AUTOPILOT_VERSION: lambda now: autopilot_version(c.system_id),
            M.MAVLINK_MSG_ID_MISSION_CURRENT: self.missions.current_message,
            **self.reporter.builders(),
        }
        intervals = default_intervals(c.heartbeat_period, c.telemetry_period)
        self.rates = {name: MessageRates(intervals) for name in link.endpoints}
        self._last_reported: tuple[int, int, int] | None = None

    def install(self) -> None:
        """Register the message handlers and commands on the link."""
        link, p, mi = self.link, self.params, self.missions
        for kind, fn in (("PARAM_REQUEST_LIST", p.on_request_list),
                         ("PARAM_REQUEST_READ", p.on_request_read), ("PARAM_SET", p.on_set),
                         ("MISSION_REQUEST_LIST", mi.on_request_list),
                         ("MISSION_REQUEST_INT", mi.on_request_item),
                         ("MISSION_REQUEST", mi.on_request_item),
                         ("MISSION_ACK", mi.on_ack), ("MISSION_COUNT", mi.on_count),
                         ("MISSION_ITEM_INT", mi.on_item), ("MISSION_ITEM", mi.on_item),
                         ("MISSION_CLEAR_ALL", mi.on_clear_all),
                         ("MISSION_SET_CURRENT", mi.on_set_current_msg)):
            link.handlers[kind] = self._targeted(kind, fn)
        link.handlers["TIMESYNC"] = self._on_timesync
        link.handlers["FILE_TRANSFER_PROTOCOL"] = self._on_ftp
        sysid = link.config.system_id
        link.commands.update({
            M.MAV_CMD_REQUEST_MESSAGE: self._cmd_request_message,
            M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
                lambda msg, now: link.reply_after_ack(autopilot_version(sysid)),
            M.MAV_CMD_SET_MESSAGE_INTERVAL: self._cmd_set_interval,
            M.MAV_CMD_GET_MESSAGE_INTERVAL: self._cmd_get_interval,
            M.MAV_CMD_DO_SET_MISSION_CURRENT: self._cmd_set_mission_current,
        })

    # ------------------------------------------------------------------ outgoing
    def poll(self, now: float) -> None:
        """Time-driven work: mission upload retries, then every stream due."""
        for (ep, addr), msg in self.missions.poll(now):
            ep.send(msg, addr)
        self.send_due(now)

    def send_due(self, now: float) -> None:
        rep = self.reporter
        rep.step(now)
        fields = rep.heartbeat_fields()
        if fields != self._last_reported:
            self._last_reported = fields
            for rates in self.rates.values():
                rates.force(M.MAVLINK_MSG_ID_HEARTBEAT)
        if rep.home_changed and rep.telemetry is not None:
            rep.home_changed = False
            for rates in self.rates.values():
                rates.force(M.MAVLINK_MSG_ID_HOME_POSITION)
        built: dict[int, Any] = {}  # one build per message id per poll, shared by links
        for name, ep in self.link.endpoints.items():
            rates = self.rates[name]
            for msg_id in rates.due(now):
                if msg_id not in built:
                    builder = self.messages.get(msg_id)
                    built[msg_id] = None if builder is None else builder(now)
                if built[msg_id] is not None:
                    ep.send(built[msg_id])
                    rates.sent(msg_id, now)

    # ------------------------------------------------------------------ incoming
    def _targeted(self, kind: str, fn: Callable[[Any, float, Any], list[Any]]) -> Callable[
            [UdpEndpoint, Any, Address, float], None]:
        """A handler for a protocol service: ignore (and count) messages for other
        systems, send the service's replies back to the sender. The service gets the
        sender as an opaque ``partner`` ``(endpoint, address)`` for later sends."""
        c = self.link.config

        def handler(ep: UdpEndpoint, msg: Any, addr: Address, now: float) -> None:
            if msg.target_system not in (0, c.system_id) or \
                    msg.target_component not in (0, c.component_id):
                self.counters[f"{kind.lower()}.other_target"] += 1
                return
            for reply in fn(msg, now, (ep, addr)):
                ep.send(reply, addr)
        return handler

    def _on_timesync(self, ep: UdpEndpoint, msg: Any, addr: Address, now: float) -> None:
        if msg.tc1 != 0:  # an answer to a request we never send
            self.counters["timesync.ignored"] += 1
            return
        ep.send(M.MAVLink_timesync_message(int(round(now * 1e9)), msg.ts1), addr)

    def _on_ftp(self, ep: UdpEndpoint, msg: Any, addr: Address, now: float) -> None:
        reply = self.ftp.reply(msg)
        if reply is not None:
            ep.send(reply, addr)

    def _message_id(self, value: float, what: str) -> int | None:
        if math.isfinite(value) and value == int(value) and int(value) in self.messages:
            return int(value)
        self.counters[f"{what}.unsupported"] += 1
        return None

    def _cmd_request_message(self, msg: Any, now: float) -> int:
        msg_id = self._message_id(msg.param1, "request_message")
        if msg_id is None:
            return M.MAV_RESULT_UNSUPPORTED
        reply = self.messages[msg_id](now)
        if reply is None:  # e.g. HOME_POSITION before any telemetry
            self.counters["request_message.unavailable"] += 1
            return M.MAV_RESULT_TEMPORARILY_REJECTED
        return self.link.reply_after_ack(reply)

    def _cmd_rates(self) -> MessageRates | None:
        ep = self.link.command_link
        return None if ep is None else self.rates.get(ep.name)

    def _cmd_set_interval(self, msg: Any, now: float) -> int:
        msg_id = self._message_id(msg.param1, "message_interval")
        rates = self._cmd_rates()
        if msg_id is None or rates is None:
            return M.MAV_RESULT_UNSUPPORTED
        ok = rates.set_interval(msg_id, msg.param2)
        return M.MAV_RESULT_ACCEPTED if ok else M.MAV_RESULT_DENIED

    def _cmd_get_interval(self, msg: Any, now: float) -> int:
        msg_id = self._message_id(msg.param1, "message_interval")
        rates = self._cmd_rates()
        if msg_id is None or rates is None:
            return M.MAV_RESULT_UNSUPPORTED
        return self.link.reply_after_ack(
            M.MAVLink_message_interval_message(msg_id, rates.interval_us(msg_id)))

    def _cmd_set_mission_current(self, msg: Any, now: float) -> int:
        seq = msg.param1
        ok = math.isfinite(seq) and seq == int(seq) and self.missions.set_current(int(seq))
        return M.MAV_RESULT_ACCEPTED if ok else M.MAV_RESULT_DENIED

    def all_counters(self) -> Counter[str]:
        out: Counter[str] = Counter(self.counters)
        out.update({f"params.{k}": v for k, v in self.params.counters.items()})
        out.update({f"mission.{k}": v for k, v in self.missions.counters.items()})
        out.update({f"ftp.{k}": v for k, v in self.ftp.counters.items()})
        return out
