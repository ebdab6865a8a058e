"""The bridge node (``skyloop bridge``): the vehicle's MAVLink endpoint on the bus.

Design (issue 4): **the commander lives here**, next to the MAVLink endpoint that
answers for it. :class:`~mavlink_bridge.vehicle_link.VehicleLink` (PX4 SITL ports: API
link 14580 -> 14540, GCS link 18570 -> 14550) answers heartbeats, COMMAND_LONG (arm,
takeoff, land, set mode) and validates setpoints against the commander object passed
in (``sitl.commander.Commander`` in practice; the ``skyloop`` command wires it, since
this package does not import ``sitl``). The simulator only flies what ``cmd_vel`` says;
the commander decides what that is, so its failsafes work whatever the policy does:

* each odometry message (one per control step, stamped with the stack time) is a
  commander step: ``commander.step(now, sample)``;
* in OFFBOARD with a body-frame setpoint, ``cmd_vel`` carries that setpoint as it
  arrived (``frame_id = "base_link"``: body-horizontal FLU + yaw rate, the simulator
  rotates it by its estimated yaw exactly as ``EpisodeSim.step_body``); otherwise it
  carries the commander's world ENU output (HOLD: zero, LAND: descend, ...);
* a setpoint's ``time_boot_ms`` is the stack time of the step it answers (the policy
  node sends it so); ``cmd_vel``'s stamp is that time, so the simulator matches by step.

Lockstep: at the odometry of step ``k`` the bridge, if in OFFBOARD, waits (servicing
MAVLink) until the setpoint for step ``k`` arrives or the mode changes, then steps the
commander and publishes. If no setpoint comes within ``lockstep_timeout_s`` of *wall*
time (2 s; a healthy step takes milliseconds) the policy is taken as gone: the step is
flown without it (the last setpoint, as PX4 would), and after 1.0 s of stack time the
commander's setpoint-loss failsafe acts as in real time (logged and counted in
``missed``: such a run is no longer deterministic). Real time: setpoints are
forwarded as they arrive (once per step: the client's 20 Hz re-sends carry the same
step stamp and only feed the commander's stream); commander steps follow the
odometry, so setpoint loss for 1.0 s falls to HOLD, then LAND, as in PX4.

Commander time: wall seconds since the bridge started until the first odometry, then
``base + stack time`` (rebased if the simulator restarts), so it never goes backwards.
"""

from __future__ import annotations

import logging
import os
import queue
import select
import time
from collections.abc import Callable
from typing import Any

from bus import keys
from bus import messages as m
from bus.node import Bus
from mavlink_bridge.interfaces import VehicleTelemetry, VelocityCommand
from mavlink_bridge.vehicle_link import VehicleLink, VehicleLinkConfig

log = logging.getLogger("skyloop.bridge")
BODY_FRAME = "base_link"
SampleFactory = Callable[[float, float, float, float], Any]  # (z, vz, yaw, agl) -> sample
Ground = Callable[[str, float, float], float]  # (scenario, x, y) -> terrain height


class BridgeNode:
    """Commander + VehicleLink + bus (see the module docstring)."""

    def __init__(self, bus: Bus, commander: Any, make_sample: SampleFactory,
                 vehicle: str = "uav1", link_config: VehicleLinkConfig | None = None,
                 lockstep: bool = True, ground: Ground | None = None,
                 lockstep_timeout_s: float = 2.0) -> None:
        self.bus, self.commander, self.make_sample = bus, commander, make_sample
        self.lockstep, self.ground = lockstep, ground
        self.lockstep_timeout_s = lockstep_timeout_s
        self.missed = 0  # lockstep steps taken without their setpoint
        self.link = VehicleLink(commander, link_config, on_setpoint=self._on_setpoint)
        original = self.link.handlers["SET_POSITION_TARGET_LOCAL_NED"]

        def on_setpoint_msg(ep: Any, msg: Any, addr: Any, now: float) -> None:
            self._ms = int(msg.time_boot_ms)
            original(ep, msg, addr, now)

        self.link.handlers["SET_POSITION_TARGET_LOCAL_NED"] = on_setpoint_msg
        self.pub = bus.publisher(keys.CMD_VEL, vehicle)
        self._q: queue.Queue[tuple[str, Any]] = queue.Queue()
        self._wake_r, self._wake_w = os.pipe()  # bus callbacks wake the select loop
        os.set_blocking(self._wake_r, False)
        for topic in (keys.EPISODE, keys.ODOM):
            bus.subscribe(topic, vehicle, lambda msg, t=topic: self._push(t, msg))
        self._t0 = time.monotonic()
        self._base: float | None = None
        self._last_stamp = -1
        self.now = 0.0
        self._ms = -1
        self._sp: tuple[VelocityCommand, int] | None = None  # latest setpoint + its ms
        self._waiting: int | None = None  # lockstep: stamp (ns) we wait a setpoint for
        self._matched = False
        self._forwarded = -1  # real time: newest step stamp forwarded
        self._early: tuple[VelocityCommand, int] | None = None  # real time: ahead of odom
        self.scenario = ""
        self.published = 0
        self.stale = 0

    def _push(self, topic: str, msg: Any) -> None:
        self._q.put((topic, msg))
        try:
            os.write(self._wake_w, b"x")
        except OSError:  # closed, or the pipe is full (the loop is awake anyway)
            pass

    # ------------------------------------------------------------------ time
    def _clock(self) -> float:
        if self._base is None:
            self.now = max(self.now, time.monotonic() - self._t0)
        return self.now

    def _stack_time(self, stamp_ns: int) -> float:
        if self._base is None or stamp_ns <= self._last_stamp:  # first step, or a restart
            self._forwarded = -1
            self._base = max(self.now, time.monotonic() - self._t0) + 0.1 - stamp_ns / 1e9
        self._last_stamp = stamp_ns
        self.now = self._base + stamp_ns / 1e9
        return self.now

    # ------------------------------------------------------------------ MAVLink side
    def _on_setpoint(self, cmd: VelocityCommand, now: float) -> None:
        self.commander.setpoint(now, cmd.vx, cmd.vy, cmd.vz, cmd.yaw_rate,
                                body=cmd.frame_is_body, yaw=cmd.yaw)
        self._sp = (cmd, self._ms)
        stamp = self._ms * 1_000_000
        if self.lockstep:
            if self._waiting is not None:
                if stamp == self._waiting:
                    self._matched = True
                else:
                    self.stale += 1
        elif str(self.commander.state) == "OFFBOARD" and self._body_setpoint():
            if self._forwarded < stamp <= self._last_stamp:
                # a fresh answer to a step seen (re-sends carry the same stamp: they keep
                # the commander's stream alive; the simulator flies the newest anyway)
                self._forwarded = stamp
                self._publish_body(cmd, stamp)
            elif stamp > self._last_stamp:  # its odometry is still on the way to us
                self._early = (cmd, stamp)

    def _body_setpoint(self) -> bool:
        return self._sp is not None and self._sp[0].frame_is_body and self._sp[0].yaw is None

    def _publish_body(self, cmd: VelocityCommand, stamp_ns: int) -> None:
        self.pub.put(m.twist_stamped(cmd.vx, cmd.vy, cmd.vz, cmd.yaw_rate, stamp_ns / 1e9,
                                     frame_id=BODY_FRAME))
        self.published += 1

    def _service(self, timeout: float) -> None:
        """Wait up to ``timeout`` for MAVLink traffic, then handle it."""
        if timeout > 0:
            select.select(self.link.fileno(), [], [], timeout)
        self.link.poll(self._clock())
        for event in self.commander.pop_events():
            log.info("commander at %.2f s: %s", event.time, event.text)
            self.link.statustext(event.text, event.severity)

    # ------------------------------------------------------------------ bus side
    def _on_episode(self, msg: Any) -> None:
        if msg.event == m.START:
            self.scenario = msg.scenario

    def _agl(self, x: float, y: float, z: float) -> float:
        if self.ground is None or not self.scenario:
            return z
        return z - self.ground(self.scenario, x, y)

    def _on_odom(self, msg: Any, stop: Callable[[], bool]) -> None:
        stamp = m.nanoseconds(msg.header.stamp)
        now = self._stack_time(stamp)
        (x, y, z), (vx, vy, vz), q = m.odometry_values(msg)
        yaw = m.yaw_of(q)
        self.link.update_telemetry(VehicleTelemetry(now, (x, y, z), (vx, vy, vz),
                                                    (0.0, 0.0, yaw)))
        if self.lockstep and str(self.commander.state) == "OFFBOARD":
            # the setpoint may already be here (read while this odometry was queued)
            self._waiting = stamp
            self._matched = self._sp is not None and self._sp[1] * 1_000_000 == stamp
            deadline = time.monotonic() + self.lockstep_timeout_s
            while not (self._matched or stop()) and str(self.commander.state) == "OFFBOARD":
                if time.monotonic() > deadline:  # the policy is gone or stuck: step without
                    self.missed += 1
                    log.warning("lockstep: no setpoint for stack time %.1f s within %.1f s "
                                "(wall); stepping without it", stamp / 1e9,
                                self.lockstep_timeout_s)
                    break
                self._service(0.05)
            self._waiting = None
        out = self.commander.step(now, self.make_sample(z, vz, yaw, self._agl(x, y, z)))
        early, self._early = self._early, None
        if early is not None and early[1] == stamp and str(self.commander.state) == "OFFBOARD":
            self._forwarded = stamp  # real time: the setpoint beat its odometry here
            self._publish_body(*early)
        if str(self.commander.state) == "OFFBOARD" and self._body_setpoint():
            if self.lockstep:
                assert self._sp is not None
                self._publish_body(self._sp[0], stamp)
        else:
            self.pub.put(m.twist_stamped(out.vx, out.vy, out.vz, out.yaw_rate, stamp / 1e9))
            self.published += 1

    def spin_once(self, stop: Callable[[], bool], timeout: float = 0.1) -> None:
        """Wait up to ``timeout`` for bus or MAVLink input; handle all of it."""
        ready, _, _ = select.select([self._wake_r, *self.link.fileno()], [], [], timeout)
        if self._wake_r in ready:
            try:
                while os.read(self._wake_r, 4096):
                    pass
            except BlockingIOError:
                pass
        try:
            topic, msg = self._q.get_nowait()
        except queue.Empty:
            topic = None
        while topic is not None:
            if topic == keys.EPISODE:
                self._on_episode(msg)
            else:
                self._on_odom(msg, stop)
            try:
                topic, msg = self._q.get_nowait()
            except queue.Empty:
                topic = None
        self._service(0.0)

    def run(self, stop: Callable[[], bool]) -> None:
        while not stop():
            self.spin_once(stop)

    def close(self) -> None:
        self.link.close()
        for fd in (self._wake_r, self._wake_w):
            os.close(fd)


