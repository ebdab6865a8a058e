"""The bridge node (``skyloop bridge``): the vehicle's MAVLink face on the bus.

Design (issue 5): the commander and its failsafes live in the vehicle (``skyloop sim``,
:mod:`sitl.node.vehicle_service`), so they act even when this process dies. The bridge is
only the MAVLink endpoint: :class:`~mavlink_bridge.vehicle_link.VehicleLink` (PX4 SITL
ports: API link 14580 -> 14540, GCS link 18570 -> 14550) answers heartbeats and
COMMAND_LONG for a :class:`CommanderProxy`, and forwards setpoints.

* **Commands** (arm, disarm, takeoff, land, set mode, RTL): the proxy sends each as a
  Zenoh query to the sim (``skyloop/<vehicle>/command``, ``VehicleCommand`` ->
  ``CommandAck``) and waits up to ``command_timeout_s``; the sim answers within a control
  step. No answer in time (sim gone or stuck): the command is answered
  TEMPORARILY_REJECTED and counted in :attr:`CommanderProxy.timeouts` -- never a crash.
* **State** (heartbeat mode, armed, failsafe -> MAV_STATE_CRITICAL): the newest of the
  sim's ``status`` messages and the command answers (by ``revision``). Every event a
  status carries (transitions, failsafes, refusals) goes out as a STATUSTEXT.
* **Setpoints**: every valid SET_POSITION_TARGET_LOCAL_NED is published on ``cmd_vel``
  as a ``VelocitySetpoint`` (frame, velocity, yaw rate or heading: ``bus/msg``) as it
  arrives, stamped with its ``time_boot_ms`` (the policy node sends the stack time of
  the step it answers, so the sim matches by step). A setpoint identical to the
  previous one, ``time_boot_ms`` included (the policy's 20 Hz re-sends in real time),
  is not forwarded again (``resends``), so the log holds each step's action once.
  ``time_boot_ms`` 0 means "not stamped" (MAVProxy's ``velocity``): each such setpoint
  is forwarded, as PX4 takes every setpoint as a fresh one, so an unstamped stream
  keeps OFFBOARD alive.
* **Parameters**: the link's parameter table (:mod:`mavlink_bridge.gcs.params`, persisted per
  vehicle; ``param_overrides`` from ``--param`` win for this run, not persisted) is the
  one ground stations read and set. Every accepted PARAM_SET goes out on the bus
  (``skyloop/<vehicle>/params``, ``Parameter``), and every value somebody chose (the
  file's, the overrides: :meth:`~mavlink_bridge.gcs.params.ParamServer.explicit`) does
  whenever the sim appears (first status, or a status whose clock went back: a
  restarted sim), so the sim (commander, autopilot) and perception (``SKY_ICO_RADIUS``)
  fly with the values a ground station set; defaults nobody touched are not sent, so a
  node's own ``--param`` stands (``skyloop up`` gives the bridge the same ones).
* **Telemetry**: LOCAL_POSITION_NED and ATTITUDE from the sim's estimated ``odom``, the
  newest one when the loop runs: odometry comes every control step (hundreds a second in
  lockstep), telemetry goes out at 10 Hz, so an odometry message wakes the loop only when
  it has not run for ``ODOM_WAKE_S`` (20 ms; in lockstep each step's setpoint wakes it).
* **Goals** (:mod:`mavlink_bridge.gcs.goals`): missions, DO_REPOSITION and
  SET_POSITION_TARGET_GLOBAL_INT become PoseStamped goals on ``goal``; progress
  (MISSION_CURRENT, MISSION_ITEM_REACHED) follows the sim's ``episode`` events.
* **Overload**: the sim's ``status`` and ``episode`` messages wait for the loop in a
  bounded queue (``queue_size``); when it is full the oldest is dropped (the newest state
  matters) and counted (``dropped``, in the node's last log line), so a flood cannot
  grow memory.
* **Presence**: the endpoint is serviced (heartbeats sent, MAVLink read) only while the
  sim's status is fresh (one within ``vehicle_timeout_s``; the sim sends one a second):
  like a PX4 that is not running, a vehicle whose sim has not started or has died sends
  no heartbeat, so clients do not command it too early.

* **Readiness**: once its MAVLink sockets are bound and its publishers and subscribers
  declared, the node holds the readiness token ``skyloop/<vehicle>/ready/bridge``
  (``bus.node.Bus.declare_ready``), what ``skyloop up`` waits on; gone on :meth:`close`.
  Ready is not present: it sends no heartbeat until the sim's status comes.

The link's clock is the bridge's wall clock (seconds since it started).
"""

from __future__ import annotations

import logging
import math
import os
import queue
import select
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bus import keys
from bus import messages as m
from bus.node import Bus
from mavlink_bridge.gcs.goals import GoalService
from mavlink_bridge.interfaces import VehicleTelemetry, VelocityCommand
from mavlink_bridge.vehicle_link import VehicleLink, VehicleLinkConfig

log = logging.getLogger("skyloop.bridge")
ODOM_WAKE_S = 0.02  # s: odometry wakes the loop only when it has not run for this long


@dataclass(frozen=True)
class ProxyVerdict:
    """A verdict from the sim's commander (``busy``: it did not answer in time)."""

    accepted: bool
    reason: str = ""


class CommanderProxy:
    """:class:`~mavlink_bridge.interfaces.CommanderLike` for a commander in the sim
    (see the module docstring). Not thread-safe: use it from the bridge's loop."""

    def __init__(self, bus: Bus, vehicle: str, timeout_s: float = 1.0) -> None:
        self.bus, self.vehicle, self.timeout_s = bus, vehicle, timeout_s
        self.timeouts = 0
        self.revision = -1
        self._vehicle_time = -math.inf  # of the newest status (a smaller one: a new sim)
        self._state, self._armed, self._landed, self._failsafe = "DISARMED", False, True, False

    # ------------------------------------------------------------------ state
    @property
    def state(self) -> str:
        return self._state

    @property
    def armed(self) -> bool:
        return self._armed

    @property
    def landed(self) -> bool:
        return self._landed

    @property
    def failsafe(self) -> bool:
        return self._failsafe

    def update(self, msg: Any) -> bool:
        """Take a ``VehicleStatus`` or ``CommandAck`` if it is not older than what we
        have (a status whose clock went back comes from a restarted sim: taken); True if
        taken."""
        vehicle_time = getattr(msg, "vehicle_time", None)
        restarted = vehicle_time is not None and vehicle_time < self._vehicle_time
        if vehicle_time is not None:
            self._vehicle_time = float(vehicle_time)
        if int(msg.revision) < self.revision and not restarted:
            return False
        self.revision = int(msg.revision)
        self._state, self._armed = str(msg.state), bool(msg.armed)
        self._landed, self._failsafe = bool(msg.landed), bool(msg.failsafe)
        return True

    # ------------------------------------------------------------------ requests
    def _request(self, command: str, mode: str = "", param1: float = math.nan) -> ProxyVerdict:
        ack = self.bus.query(keys.COMMAND, self.vehicle, m.vehicle_command(command, mode, param1),
                             m.COMMAND_ACK, self.timeout_s)
        if ack is None:
            self.timeouts += 1
            log.warning("the sim did not answer '%s %s' within %.1f s", command, mode,
                        self.timeout_s)
            return ProxyVerdict(False, "busy")
        self.update(ack)
        return ProxyVerdict(bool(ack.accepted), str(ack.reason))

    def arm(self, now: float) -> ProxyVerdict:
        return self._request("arm")

    def disarm(self, now: float, force: bool = False) -> ProxyVerdict:
        return self._request("disarm", param1=1.0 if force else 0.0)

    def takeoff(self, now: float, altitude: float | None = None) -> ProxyVerdict:
        return self._request("takeoff", param1=math.nan if altitude is None else altitude)

    def land(self, now: float) -> ProxyVerdict:
        return self._request("land")

    def set_mode(self, now: float, state: str) -> ProxyVerdict:
        return self._request("set_mode", mode=str(state))

    def return_home(self, now: float) -> ProxyVerdict:
        return self._request("rtl")


class BridgeNode:
    """VehicleLink + CommanderProxy + bus (see the module docstring)."""

    def __init__(self, bus: Bus, vehicle: str = "uav1",
                 link_config: VehicleLinkConfig | None = None,
                 command_timeout_s: float = 1.0, vehicle_timeout_s: float = 3.0,
                 param_overrides: dict[str, float] | None = None,
                 queue_size: int = 256) -> None:
        self.bus = bus
        self.vehicle_timeout_s = vehicle_timeout_s
        self._status_wall = -math.inf  # monotonic time of the last status
        self._status_time = math.inf  # the newest status's vehicle_time
        self.commander = CommanderProxy(bus, vehicle, command_timeout_s)
        self.link = VehicleLink(self.commander, link_config, on_setpoint=self._on_setpoint)
        for name, value in (param_overrides or {}).items():
            self.link.params.override(name, value)
        self.param_pub = bus.publisher(keys.PARAMS, vehicle)
        self.link.params.on_change = self._publish_param
        self.params_published = 0
        self.pub = bus.publisher(keys.CMD_VEL, vehicle)
        self._q: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=queue_size)
        self.dropped = 0  # bus messages dropped from a full queue (see the module doc)
        self._count_lock = threading.Lock()
        self._wake_r, self._wake_w = os.pipe()  # bus callbacks wake the select loop
        os.set_blocking(self._wake_r, False)
        for topic in (keys.STATUS, keys.EPISODE):
            bus.subscribe(topic, vehicle, lambda msg, t=topic: self._push(t, msg))
        self._odom: Any = None  # the newest odometry
        self._odom_taken: Any = None  # ... the loop has handled
        self._spun = -math.inf  # monotonic time the loop last handled input
        bus.subscribe(keys.ODOM, vehicle, self._offer_odom)
        # Goals from the ground station (mavlink_bridge.gcs.goals) -> the goal topic.
        goal_pub = bus.publisher(keys.GOAL, vehicle)
        self.goals = GoalService(self.link, lambda p: goal_pub.put(m.pose_stamped(p, 0.0)))
        self.goals.install()
        self._t0 = time.monotonic()
        self._last: tuple | None = None  # the last forwarded setpoint (re-send filter)
        self.published = 0
        self.resends = 0
        self.statustexts = 0
        # The MAVLink sockets bound (VehicleLink), publishers and subscribers declared:
        # what ``skyloop up`` waits on (the token ``skyloop/<vehicle>/ready/bridge``).
        self.ready = bus.declare_ready(vehicle, "bridge")

    def _push(self, topic: str, msg: Any) -> None:
        """Zenoh's callback: queue the message; a full queue drops its oldest."""
        while True:
            try:
                self._q.put_nowait((topic, msg))
                break
            except queue.Full:
                try:
                    self._q.get_nowait()
                except queue.Empty:
                    continue
                with self._count_lock:  # Zenoh calls back from several threads
                    self.dropped += 1
                    dropped = self.dropped
                if dropped in (1, 10, 100) or dropped % 1000 == 0:
                    log.warning("overloaded: %d bus messages dropped so far", dropped)
        self._wake()

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except OSError:  # closed, or the pipe is full (the loop is awake anyway)
            pass

    def _offer_odom(self, msg: Any) -> None:
        """Odometry comes every control step (300 a second in lockstep) and telemetry
        goes out at 10 Hz: keep the newest, and wake the loop only when it has not run
        for ``ODOM_WAKE_S`` (in lockstep each step's setpoint wakes it anyway)."""
        self._odom = msg
        if time.monotonic() - self._spun >= ODOM_WAKE_S:
            self._wake()

    def clock(self) -> float:
        """The link's clock: wall seconds since the bridge started."""
        return time.monotonic() - self._t0

    # ------------------------------------------------------------------ MAVLink side
    def _on_setpoint(self, cmd: VelocityCommand, now: float, time_boot_ms: int) -> None:
        key = (time_boot_ms, cmd)
        if key == self._last and time_boot_ms != 0:
            self.resends += 1
            return
        self._last = key
        heading = cmd.yaw is not None
        self.pub.put(m.velocity_setpoint((cmd.vx, cmd.vy, cmd.vz),
                                         cmd.yaw if heading else cmd.yaw_rate,
                                         time_boot_ms / 1000.0, body=cmd.frame_is_body,
                                         heading=heading))
        self.published += 1

    def _publish_param(self, name: str, value: float) -> None:
        self.param_pub.put(m.parameter(name, value))
        self.params_published += 1

    # ------------------------------------------------------------------ bus side
    def _on_status(self, msg: Any) -> None:
        vehicle_time = float(msg.vehicle_time)
        if not self.vehicle_present or vehicle_time < self._status_time:
            chosen = self.link.params.explicit()
            log.info("vehicle present: sending %d chosen parameters", len(chosen))
            for name, value in chosen.items():
                self._publish_param(name, value)
        self._status_time = vehicle_time
        self._status_wall = time.monotonic()
        self.commander.update(msg)
        for text, severity in zip(msg.event_texts, msg.event_severities, strict=False):
            log.info("vehicle: %s", text)
            self.link.statustext(str(text), int(severity))
            self.statustexts += 1

    def _on_odom(self, msg: Any) -> None:
        (x, y, z), (vx, vy, vz), q = m.odometry_values(msg)
        self.link.update_telemetry(VehicleTelemetry(self.clock(), (x, y, z), (vx, vy, vz),
                                                    (0.0, 0.0, m.yaw_of(q))))

    def spin_once(self, timeout: float = 0.1) -> None:
        """Wait up to ``timeout`` for bus or MAVLink input; handle all of it."""
        links = self.link.fileno() if self.vehicle_present else []
        ready, _, _ = select.select([self._wake_r, *links], [], [], timeout)
        if self._wake_r in ready:
            try:
                while os.read(self._wake_r, 4096):
                    pass
            except BlockingIOError:
                pass
        while True:
            try:
                topic, msg = self._q.get_nowait()
            except queue.Empty:
                break
            if topic == keys.STATUS:
                self._on_status(msg)
            else:
                self.goals.on_episode(msg, self.clock())
        odom = self._odom
        if odom is not self._odom_taken:
            self._odom_taken = odom
            self._on_odom(odom)
        self._spun = time.monotonic()
        if self.vehicle_present:
            self.link.poll(self.clock())

    @property
    def vehicle_present(self) -> bool:
        """Whether the sim's status is fresh (see the module docstring)."""
        return time.monotonic() - self._status_wall <= self.vehicle_timeout_s

    def run(self, stop: Callable[[], bool]) -> None:
        while not stop():
            self.spin_once()

    def counters(self) -> dict[str, int]:
        """What the node did: setpoints forwarded and re-sends skipped, STATUSTEXTs,
        parameters published, commands the sim did not answer, bus messages dropped."""
        return {"setpoints": self.published, "resends": self.resends,
                "statustexts": self.statustexts, "params_published": self.params_published,
                "command_timeouts": self.commander.timeouts, "dropped": self.dropped}

    def close(self) -> None:
        """Drop the readiness token, close the MAVLink links and the wake-up pipe."""
        self.ready.close()
        self.link.close()
        for fd in (self._wake_r, self._wake_w):
            os.close(fd)
