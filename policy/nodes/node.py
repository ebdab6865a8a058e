"""The policy node (``skyloop policy``): observations -> 3-frame state -> actor -> MAVLink.

It sits where a MAVSDK offboard client sits in PX4 SITL: an
:class:`~mavlink_bridge.offboard_client.OffboardClient` listening on UDP 14540. At
startup it flies the MAVSDK offboard recipe: wait for the vehicle's heartbeat, set a
zero setpoint (streamed at 20 Hz), arm, take off, start offboard (setpoints stream
first, then the mode switch; the heartbeat must show OFFBOARD). Then it prints
``READY_LINE`` and flies.

Per observation (``skyloop/<vehicle>/observation``, 35 values with episode and step):
the :class:`~perception.observation.FrameStacker` is reset at step 0 and whenever the
episode changes (never carried across episodes), the actor maps the stacked state to
``(vx, vy, vz, yaw_rate)`` body-horizontal, clipped to [-2, 2] and rounded to float32
(the env does the same), sent as SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_BODY_NED with
the velocity + yaw-rate type mask.

**New weights** (``--weights-from-bus``): a :class:`~policy.nodes.weights.WeightsFollower`
decodes actor weights a learner publishes between observations and swaps them in where
the frame stacker resets (the episode boundary), never mid-episode; ``weights_version``
is the version flying.

**Holding between goals** (``hold``, ``skyloop up --goals gcs``): the sim flies
episodes only toward goals from a ground station, and nothing is observed between them.
At startup the node waits for the takeoff to complete (Hold) before OFFBOARD (no episode
will place the vehicle airborne). As a MAVSDK companion would, it then streams a zero
velocity setpoint at 20 Hz (the vehicle hovers in OFFBOARD, no setpoint-loss
failsafe): from OFFBOARD until the first observation, and from each episode's END
(``episode`` topic) until the next episode's first observation; observations of an
ended episode are dropped. At the first observation of a new episode, if the vehicle is
armed in HOLD (a ground station paused it, or a failsafe held it) the node asks for
OFFBOARD again: a new goal is the ground station's word to fly.

**Parameters.** A controller flies only under the parameters it was trained under
(``bus.params`` marks them ``task_field``: the icosahedron radius, the autopilot's speed
limits; an actor file records their values). When one differs, seen on the ``params``
topic or in an observation's recorded radius, the node stops answering steps, asks the
vehicle to hold and sends a STATUSTEXT naming the parameter (the bridge shows it to
ground stations); when all are back, it flies again (OFFBOARD at the next observation).

**Step matching.** A setpoint sent for an observation carries, as ``time_boot_ms``, the
stack time (ms) of that observation; the vehicle's bridge uses it to tell the simulator
which step the command is for. Once in OFFBOARD the client's own timer re-sends stop:
in lockstep each observation gives exactly one setpoint (10 Hz of stack time, more than
PX4's 2 Hz); in real time the node re-sends the newest every 50 ms as MAVSDK does, with
the same step stamp, so the bridge forwards each step's setpoint once.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from bus import keys, params
from bus import messages as m
from bus.node import Bus, inbox_drops
from bus.task import TASK, TaskSpec
from mavlink_bridge.modes import AUTO_LOITER, AUTO_TAKEOFF, OFFBOARD
from mavlink_bridge.offboard_client import (
    CommandRejected,
    OffboardClient,
    OffboardClientConfig,
    OffboardError,
)
from mavlink_bridge.transport import mavlink
from perception.observation import FrameStacker, ObservationConfig

log = logging.getLogger("skyloop.policy")
READY_LINE = "SKYLOOP-POLICY-READY"
#: non-finite actions in a row after which the node stops (an actor that outputs NaN is
#: broken: flying on would only time every episode out without saying why)
MAX_BAD_ACTIONS = 5
MAX_ACTION = TASK.max_action  # bus.task
Controller = Callable[[np.ndarray], np.ndarray]


class PolicyNode:
    """Flies ``controller`` through MAVLink (see the module docstring)."""

    def __init__(self, bus: Bus, controller: Controller, vehicle: str = "uav1",
                 client_config: OffboardClientConfig | None = None, frames: int = TASK.frames,
                 dim: int = TASK.obs_dim, lockstep: bool = True, weights: Any = None,
                 hold: bool = False, trained: TaskSpec | None = None,
                 trained_observation: ObservationConfig | None = None) -> None:
        self.bus, self.controller, self.vehicle = bus, controller, vehicle
        #: the task the controller was trained under (None: it depends on no parameter,
        #: e.g. the scripted controller); default: the controller's ``trained_task``
        self.trained = trained or getattr(controller, "trained_task", None)
        #: how the observations it was trained on were made (None: not recorded; then
        #: only SKY_ICO_RADIUS is checked); default: the controller's
        self.trained_observation = trained_observation or getattr(
            controller, "trained_observation", None)
        self.weights = weights  # a policy.nodes.weights.WeightsFollower, or None
        self.lockstep = lockstep
        self.stacker = FrameStacker(frames, dim)
        self.client = OffboardClient(client_config)
        self.inbox = bus.inbox(keys.OBSERVATION, vehicle, maxsize=64)
        self.episode: int | None = None
        self.sent = 0
        self.bad_actions = 0
        self._bad_in_a_row = 0
        self.resend_period = 0.05  # real time, as MAVSDK's 20 Hz
        self._stamp_ms: int | None = None  # the stack time (ms) of the step answered
        self._next_resend = math.inf
        self.hold = hold
        self.ended = -1  # hold: the newest episode whose END was seen
        self.events = bus.inbox(keys.EPISODE, vehicle, maxsize=64) if hold else None
        self.reentries = 0  # hold: OFFBOARD asked for again at a new episode
        self.params = bus.inbox(keys.PARAMS, vehicle, maxsize=64)
        self.off_task: dict[str, str] = {}  # parameter -> why it is not as trained
        self.refusals = 0  # times the node stopped flying for off-task parameters
        self._resume = False  # parameters as trained again: OFFBOARD at the next step

    def start(self, takeoff_altitude: float | None = None, timeout: float = 30.0,
              retry_s: float = 0.5) -> None:
        """Connect, stream a zero setpoint, arm, take off, start offboard. A denial of
        arming or of OFFBOARD is tried again from arming for up to ``timeout`` s: a node
        restarted while the vehicle lies crashed and disarmed (its episode ended in a
        collision) is denied until the simulator places the vehicle for the next episode,
        and the vehicle can come down again between arming and the switch (both seen in
        the chaos test: the restarted policy exited on the denial and used up its
        restarts)."""
        self.controller(self.stacker.state)  # warm up (torch's first call is slow)
        c = self.client
        log.info("waiting up to %g s for the vehicle's heartbeat", timeout)
        c.wait_heartbeat(timeout)
        c.set_velocity_body(0.0, 0.0, 0.0, 0.0)
        deadline = time.monotonic() + timeout
        while True:
            try:
                self._join(takeoff_altitude, timeout)
                break
            except CommandRejected as err:
                if time.monotonic() + retry_s > deadline:
                    raise
                log.info("%s: the vehicle may be down between episodes; trying again", err)
                time.sleep(retry_s)
        # From now on the node paces the stream itself (see the module docstring);
        # holding, the client's timer streams the zero setpoint until an observation.
        if not self.hold:
            self._stream_zero(False)
        log.info("offboard: flying %s (weights version %d)",
                 getattr(self.controller, "name", "controller"), self.weights_version)

    def _join(self, takeoff_altitude: float | None, timeout: float) -> None:
        """Arm, take off (or join the vehicle in the air), start offboard; a denial
        raises ``CommandRejected``."""
        c = self.client
        c.arm()
        try:
            c.takeoff(takeoff_altitude)
        except OffboardError:
            if not c.armed:
                raise
            # armed and the takeoff refused: already flying (a restarted node joining
            # a vehicle that holds or lands after its failsafe)
            log.info("the vehicle is flying (%s): joining it in the air", c.mode)
        if self.hold:  # no episode will place it airborne: climb first (then Hold)
            c.wait(lambda: c.mode == AUTO_TAKEOFF, 5.0)
            if not c.wait(lambda: c.mode == AUTO_LOITER, timeout):
                raise OffboardError(f"takeoff did not complete within {timeout} s")
        c.start_offboard()

    def _stream_zero(self, on: bool) -> None:
        """Start (``on``: a zero setpoint, re-sent at 20 Hz by the client) or stop the
        client's own setpoint timer."""
        c = self.client
        if on:
            self._stamp_ms = None  # no re-sends of a step's setpoint while holding
            c.config.setpoint_period = self.resend_period
            c.set_velocity_body(0.0, 0.0, 0.0, 0.0)
        else:
            c.set_stream_period(math.inf)

    def _take_events(self) -> None:
        """Hold: an END of the episode flying starts the zero stream."""
        assert self.events is not None
        while (ev := self.events.get_nowait()) is not None:
            if int(ev.event) == m.END and int(ev.episode) > self.ended:
                self.ended = int(ev.episode)
                if self.episode is not None and self.episode <= self.ended:
                    self._stream_zero(True)

    def _resume_offboard(self) -> None:
        """The vehicle armed in HOLD -> OFFBOARD again (hold: a new episode; or the
        parameters are as trained again)."""
        c = self.client
        if not (c.armed and c.mode == AUTO_LOITER):
            return
        self.reentries += 1
        try:
            c.set_mode(OFFBOARD)
            log.info("OFFBOARD again")
        except OffboardError as err:
            log.warning("OFFBOARD refused (%s)", err)

    def check_param(self, name: str, value: float) -> None:
        """A parameter value seen on the bus or in an observation: flying stops while
        one the task depends on differs from what the controller was trained under
        (``bus.params.off_task``), and resumes when all are back."""
        if self.trained is None:
            return
        self._off(name, params.off_task(self.trained, name, value))

    def check_observation(self, scaling: dict) -> None:
        """An observation's scaling fields (how perception made it): flying stops while
        its face encoding, angle centring or scales differ from the trained ones (the
        radius is SKY_ICO_RADIUS's, checked by ``check_param``)."""
        t = self.trained_observation
        if t is None:
            return
        diffs = [f"{k}={scaling[k]}, trained with {getattr(t, k)}"
                 for k in ("encoding", "centre_angles", "altitude_scale", "angle_scale")
                 if k in scaling and scaling[k] != getattr(t, k)]
        self._off("observation", "; ".join(diffs) if diffs else None)

    def _off(self, key: str, why: str | None) -> None:
        """Record (or clear) one reason not to fly; refuse or resume on the change."""
        was = bool(self.off_task)
        if why is not None:
            self.off_task[key] = why
        else:
            self.off_task.pop(key, None)
        if self.off_task and not was:
            self._refuse()
        elif was and not self.off_task:
            log.info("parameters as trained again: flying from the next observation")
            self._notify("Policy: parameters as trained, flying", mavlink.MAV_SEVERITY_NOTICE)
            self._resume = True

    def _refuse(self) -> None:
        """Stop answering steps, ask the vehicle to hold, tell the ground station."""
        why = "; ".join(self.off_task.values())
        self.refusals += 1
        self._resume = False
        self._stamp_ms = None
        log.error("not flying: %s (the policy was not trained for it)", why)
        self._notify(f"Policy off: {why}", mavlink.MAV_SEVERITY_CRITICAL)
        if self.client.vehicle is not None and self.client.mode != AUTO_LOITER:
            try:
                self.client.hold()
            except OffboardError as err:
                log.warning("HOLD refused: %s", err)

    def _notify(self, text: str, severity: int) -> None:
        if self.client.vehicle is not None:
            self.client.statustext(text, severity)

    def _take_params(self) -> None:
        while (msg := self.params.get_nowait()) is not None:
            self.check_param(str(msg.name), float(msg.value))

    @property
    def weights_version(self) -> int:
        """Version of the actor flying (0: the one the node started with)."""
        return 0 if self.weights is None else self.weights.version

    def act(self, msg: object) -> np.ndarray | None:
        """One observation -> the float32 action sent (None if the actor gave NaN/inf)."""
        values = m.observation_values(msg)[-1]
        episode, step = int(msg.episode), int(msg.step)
        scaling = m.observation_scaling(msg)
        if scaling is not None:  # the radius perception used for it (SKY_ICO_RADIUS)
            self.check_param("SKY_ICO_RADIUS", scaling["radius"])
            self.check_observation(scaling)
        if self.off_task:
            return None  # not trained for these parameters: the vehicle holds
        if self.hold and episode <= self.ended:
            return None  # an ended episode's late observation: keep holding
        new = episode != self.episode
        if step == 0 or new:
            self.stacker.reset()
            self.episode = episode
            if self.weights is not None:
                self.weights.at_episode_boundary(episode)
        state = self.stacker.push(values)
        action = np.asarray(self.controller(state), dtype=np.float64).reshape(-1)
        if action.shape != (TASK.action_dim,) or not np.all(np.isfinite(action)):
            self.bad_actions += 1
            self._bad_in_a_row += 1
            log.warning("actor gave %s at episode %d step %d; nothing sent", action, episode,
                        step)
            if self._bad_in_a_row >= MAX_BAD_ACTIONS:
                raise ValueError(f"the actor gave {self._bad_in_a_row} non-finite or "
                                 f"misshapen actions in a row (episode {episode} step {step}, "
                                 f"{action.tolist()}): not flying it")
            return None
        self._bad_in_a_row = 0
        action = np.clip(action, -MAX_ACTION, MAX_ACTION).astype(np.float32)
        self._stamp_ms = (m.nanoseconds(msg.header.stamp) + 500_000) // 1_000_000
        self.client.set_velocity_body(*(float(a) for a in action), time_boot_ms=self._stamp_ms)
        self._next_resend = time.monotonic() + self.resend_period
        self.sent += 1
        if self._resume:
            self._resume = False
            self._resume_offboard()
        if self.hold and new:
            self._stream_zero(False)
            self._resume_offboard()
        return action

    def _resend_due(self) -> None:
        """Real time: re-send the newest setpoint (same step stamp) every 50 ms."""
        if self.lockstep or self._stamp_ms is None or time.monotonic() < self._next_resend:
            return
        self.client.resend()
        self._next_resend = time.monotonic() + self.resend_period

    def spin_once(self, timeout: float = 0.05) -> None:
        """Handle one observation (waiting up to ``timeout``), then service the link."""
        try:
            wait = timeout if self.lockstep else min(timeout, self.resend_period)
            msg = self.inbox.get(timeout=wait)
        except TimeoutError:
            msg = None
        self._take_params()
        if self.events is not None:
            self._take_events()
        if msg is not None:
            self.act(msg)
        if self.weights is not None:
            self.weights.poll()
        self.client.poll()
        self._resend_due()

    def run(self, stop: Callable[[], bool]) -> None:
        while not stop():
            self.spin_once()

    def counters(self) -> dict[str, int]:
        """The counters line ``skyloop policy`` prints last: setpoints ``sent``,
        ``refusals`` (holds for off-task parameters), ``bad_actions`` (non-finite), and
        what its bounded inboxes dropped (the oldest item, when one is full), per inbox
        (``dropped_<topic>``) and in total (``dropped``). Read at exit: the inboxes count
        as they drop, so a step pays nothing for it."""
        inboxes = [i for i in (self.inbox, self.params, self.events) if i is not None]
        return {"sent": self.sent, "refusals": self.refusals,
                "bad_actions": self.bad_actions, **inbox_drops(inboxes)}

    def close(self) -> None:
        self.client.close()
