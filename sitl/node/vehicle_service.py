"""The commander on the bus: requests, status, parameters (the sim's side of issue 5).

:class:`VehicleService` wraps the :class:`~sitl.commander.machine.Commander` that the simulator
node steps. Nothing here runs in Zenoh's threads and nothing blocks: the node calls
:meth:`VehicleService.serve` whenever it has a moment (every control step, and every
few milliseconds while it waits), so requests are answered within a step.

* **Requests** (``skyloop/<vehicle>/command``, a Zenoh query, ``VehicleCommand`` ->
  ``CommandAck``): ``arm``, ``disarm`` (``param1 == 1``: forced), ``takeoff``
  (``param1``: metres above the takeoff point, NaN: the default, MIS_TAKEOFF_ALT; the
  bridge has already turned NAV_TAKEOFF's AMSL altitude into this; accepted disarmed on
  the ground too, pending until arming: state TAKEOFF, armed false), ``land``, ``rtl`` and
  ``set_mode`` (``mode``: OFFBOARD, HOLD, LAND, TAKEOFF, RTL). The answer carries the
  commander's verdict and its state right after it. Unknown commands: ``unsupported``.
  OFFBOARD without a recent setpoint first gives :attr:`VehicleService.take_setpoints`
  up to ``SETPOINT_GRACE_S``: a client's "set a setpoint, then OFFBOARD" reaches the
  bridge in that order, but the bus may hand the sim the request before the setpoint
  (the query is queued natively, the setpoint waits for a Python callback).
* **Status** (``skyloop/<vehicle>/status``, ``VehicleStatus``): published when the
  state or the flags change or events happened (transitions, failsafes, refusals: each
  becomes a STATUSTEXT at the bridge), and at least every ``keepalive_s`` of wall time.
  ``revision`` counts changes so a reader keeps the newest of a status and an answer.
  Each status also carries the vehicle time of the newest setpoint the commander
  accepted (``last_setpoint_time``, not a change by itself), so a reader can time the
  setpoint-loss failsafe in the vehicle's clock.
* **Parameters** (``skyloop/<vehicle>/params``, ``Parameter``): names of
  :mod:`bus.params`; the sim's are applied at once (see :func:`apply_param`), those of
  other nodes ignored but for ``SKY_ICO_RADIUS``, perception's, which the LiDAR follows
  (its range reaches the new radius: ``EpisodeSim.ico_radius``); invalid ones (unknown,
  out of range, not finite) are counted in ``param_rejects`` and logged.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from bus import keys, params
from bus import messages as m
from bus.node import Bus
from sitl.commander.machine import Commander, Verdict

log = logging.getLogger("skyloop.sim")
SETPOINT_GRACE_S = 0.05  # s an OFFBOARD request waits for a setpoint still on its way


def apply_param(name: str, value: float, commander: Commander, vehicle: Any,
                sensor: Any = None) -> bool:
    """Apply a checked sim parameter to the commander, the vehicle's autopilot and the
    LiDAR (``sensor``: the ``EpisodeSim``, whose ``ico_radius`` sets its range)
    (``bus.params.ParamDef.sets``; ``vehicle``/``sensor`` None: a commander without a
    flight model, in tests); False if ``name`` sets nothing of the sim's."""
    owners = {"commander": commander.config,
              "autopilot": vehicle.autopilot if vehicle is not None else None}
    if sensor is not None:  # else SKY_ICO_RADIUS sets nothing of this sim's
        owners["lidar"] = sensor
    return params.bind(name, value, owners)


class VehicleService:
    """Requests, status and parameters of one vehicle's commander (module docstring)."""

    def __init__(self, bus: Bus, vehicle: str, commander: Commander, vehicle_model: Any,
                 keepalive_s: float = 1.0, sensor: Any = None) -> None:
        self.commander, self.vehicle_model, self.sensor = commander, vehicle_model, sensor
        self.keepalive_s = keepalive_s
        self.requests = bus.queryable(keys.COMMAND, vehicle)
        self.params = bus.inbox(keys.PARAMS, vehicle, maxsize=256)
        self.status_pub = bus.publisher(keys.STATUS, vehicle)
        self.revision = 0
        self.param_rejects = 0
        self.answered: Counter[str] = Counter()  # "<command>.<accepted|reason>"
        self._events: list[tuple[str, str, str]] = []
        self._fields: tuple | None = None
        self._next_keepalive = 0.0
        #: The node's "offer the setpoints on their way, waiting up to this many seconds
        #: for one" (see the module docstring); None: no wait.
        self.take_setpoints: Callable[[float], object] | None = None

    # ------------------------------------------------------------------ parameters
    def set_param(self, name: str, value: float) -> bool:
        """Validate and apply one parameter; False (counted, logged) if rejected."""
        try:
            v = params.check(name, value)
        except ValueError as err:
            self.param_rejects += 1
            log.warning("parameter rejected: %s", err)
            return False
        if apply_param(name, v, self.commander, self.vehicle_model, self.sensor):
            log.info("parameter %s = %g", name, v)
        return True

    def _take_params(self) -> None:
        while (msg := self.params.get_nowait()) is not None:
            self.set_param(msg.name, msg.value)

    # ------------------------------------------------------------------ requests
    def _verdict(self, now: float, msg: Any) -> Verdict:
        c, cmd, p1 = self.commander, msg.command, float(msg.param1)
        if cmd == "arm":
            return c.arm(now)
        if cmd == "disarm":
            return c.disarm(now, force=p1 == 1.0)
        if cmd == "takeoff":
            return c.takeoff(now, None if math.isnan(p1) else p1)
        if cmd == "land":
            return c.land(now)
        if cmd == "rtl":
            return c.set_mode(now, "RTL")
        if cmd == "set_mode":
            if msg.mode == "OFFBOARD" and self.take_setpoints is not None and \
                    not c.offboard_available(now):
                self.take_setpoints(SETPOINT_GRACE_S)
            return c.set_mode(now, msg.mode)
        return Verdict(False, "unsupported")

    def serve(self, now: float) -> int:
        """Answer every waiting request and apply every waiting parameter; how many
        requests were answered."""
        self._take_params()
        requests = self.requests.take()
        for req in requests:
            verdict = self._verdict(now, req.msg)
            self.answered[f"{req.msg.command}.{verdict.reason or 'accepted'}"[:40]] += 1
            self._collect()
            c = self.commander
            req.reply(m.command_ack(verdict.accepted, verdict.reason, str(c.state), c.armed,
                                    c.landed, c.failsafe, self.revision))
        return len(requests)

    def notify(self, text: str, severity: str = "warning") -> None:
        """An event of the vehicle's own (not the commander's), sent with the next
        status (a STATUSTEXT at the bridge)."""
        self._events.append((text, "vehicle", severity))

    # ------------------------------------------------------------------ status
    def _collect(self) -> bool:
        """Take the commander's events and note a change; True if anything changed."""
        c = self.commander
        events = c.pop_events()
        self._events.extend((e.text, e.kind, e.severity) for e in events)
        fields = (str(c.state), c.armed, c.landed, c.failsafe_reason, c.crashed, c.home)
        changed = bool(events) or fields != self._fields
        if changed:
            self.revision += 1
            self._fields = fields
            for e in events:
                log.info("commander at %.1f s: %s", e.time, e.text)
        return changed

    def publish_status(self, stamp_s: float, now: float, force: bool = False) -> bool:
        """Publish the status if something changed since the last one, the keepalive
        is due, or ``force``; True if published."""
        changed = self._collect()
        wall = time.monotonic()
        if not (changed or self._events or force or wall >= self._next_keepalive):
            return False
        c = self.commander
        home = (*c.home, 0.0) if c.home is not None else (math.nan, math.nan, math.nan)
        last = c.last_setpoint_time
        self.status_pub.put(m.vehicle_status(stamp_s, now, self.revision, str(c.state),
                                             c.armed, c.landed, c.failsafe_reason, c.crashed,
                                             home, self._events,
                                             last if math.isfinite(last) else math.nan))
        self._events = []
        self._next_keepalive = wall + self.keepalive_s
        return True
