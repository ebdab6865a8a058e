"""The vehicle's commander: arming, modes and failsafes as a pure, time-driven state machine.

No I/O and no flight model: requests (:meth:`Commander.arm`, :meth:`~Commander.takeoff`,
:meth:`~Commander.set_mode`, ...) are answered at once with a :class:`Verdict`; setpoints
are offered with :meth:`~Commander.setpoint`; and :meth:`~Commander.step` is called once
per control period with the time and a :class:`VehicleSample`, returning the ENU velocity
+ yaw-rate :class:`Setpoint` the velocity autopilot should fly. Transitions, failsafes and
refusals are queued as :class:`CommanderEvent` (for STATUSTEXT and the episode log).
Time is whatever clock the caller uses (simulated in lockstep, wall clock in real time);
the commander never reads a clock.

States (PX4 semantics; the bridge reports them as PX4 modes, see
``mavlink_bridge.modes``)::

    DISARMED --arm (landed)--> ARMED --takeoff--> TAKEOFF --at altitude--> HOLD
    ARMED/TAKEOFF/HOLD/LAND --set_mode OFFBOARD (setpoints streaming)--> OFFBOARD
    OFFBOARD --no setpoint for setpoint_timeout--> HOLD (failsafe)
    HOLD (failsafe) --hold_before_land--> LAND --touchdown--> DISARMED
    any in-air state --land / set_mode HOLD--> LAND / HOLD
    ARMED --disarm_preflight without takeoff--> DISARMED;  any --collision--> DISARMED

* OFFBOARD is accepted only while setpoints stream: more than ``stream_min_rate``
  setpoints per second over the last ``stream_window`` seconds (> 2 in the last 1 s by
  default) and the newest no older than ``1 / stream_min_rate``.
* Setpoint loss: at the first :meth:`step` where the newest setpoint is older than
  ``setpoint_timeout`` (strictly, with a 1 ns tolerance for float time), OFFBOARD falls
  to HOLD (a failsafe); at the first step ``hold_before_land`` seconds after that, to
  LAND (``math.inf``: hold forever). Setpoints coming back do not resume OFFBOARD by
  themselves (as PX4): the client asks for OFFBOARD again, which ends the failsafe.
* Setpoints are always recorded (so a stream can be shown before the switch) but flown
  only in OFFBOARD. Body-frame setpoints (forward, left, up) are rotated by the
  vehicle's current yaw at each step, with the same arithmetic as
  ``sitl.episode.body_to_world``; an absolute heading target becomes a yaw rate
  ``yaw_gain * wrap(target - yaw)``, clamped to ``max_yaw_rate``.
* Takeoff climbs to ``altitude`` (default ``takeoff_altitude``) above the height where
  the takeoff was accepted, at ``min(takeoff_speed, takeoff_gain * error)``, then holds.
  LAND descends at ``land_speed``; touchdown is the land detector (height above ground
  and vertical speed under thresholds for ``land_detect_time``), then it disarms.
* A collision disarms, is reported, and latches: arming is refused until :meth:`reset`.
* RTL is an extension point: the state exists (and maps to AUTO.RTL) but requesting it
  is refused as ``"unsupported_mode"`` until it has a horizontal return-home leg.

Verdict reasons: ``not_landed``, ``invalid_state``, ``not_armed``, ``in_air``,
``bad_altitude``, ``no_setpoint_stream``, ``unsupported_mode``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from enum import StrEnum
from typing import NamedTuple

EPS = 1e-9  # s, tolerance on time comparisons (float sums of control periods)


class State(StrEnum):
    """Commander states; the values are the names the MAVLink bridge maps to PX4 modes."""

    DISARMED = "DISARMED"
    ARMED = "ARMED"  # armed, idle on the ground
    TAKEOFF = "TAKEOFF"
    OFFBOARD = "OFFBOARD"
    HOLD = "HOLD"
    LAND = "LAND"
    RTL = "RTL"  # extension point, not entered yet


@dataclass
class CommanderConfig:
    """Commander parameters (PX4 equivalents in brackets)."""

    setpoint_timeout: float = 1.0  # s without a setpoint in OFFBOARD -> HOLD [COM_OF_LOSS_T]
    hold_before_land: float = 5.0  # s in failsafe HOLD -> LAND (math.inf: never)
    stream_window: float = 1.0  # s over which the setpoint rate is measured
    stream_min_rate: float = 2.0  # Hz that must be exceeded to enter OFFBOARD
    takeoff_altitude: float = 2.5  # m above the takeoff point [MIS_TAKEOFF_ALT]
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


@dataclass(frozen=True)
class Verdict:
    """The answer to a request: accepted, or refused with a short reason code."""

    accepted: bool
    reason: str = ""


ACCEPTED = Verdict(True)


@dataclass(frozen=True)
class VehicleSample:
    """What the commander needs of the vehicle each step (world ENU, SI)."""

    z: float  # m, up
    vz: float  # m/s, up
    yaw: float  # rad, CCW from east
    height_agl: float  # m above the ground below the vehicle


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


class Commander:
    """PX4-like commander for one vehicle (see the module docstring)."""

    def __init__(self, config: CommanderConfig | None = None, now: float = 0.0) -> None:
        self.config = config or CommanderConfig()
        self.rejected_setpoints = 0
        self.reset(now)

    # ------------------------------------------------------------------ state
    def reset(self, now: float = 0.0, airborne: bool = False) -> None:
        """Start over: disarmed on the ground, or (``airborne``) armed and holding."""
        self._state = State.HOLD if airborne else State.DISARMED
        self._landed = not airborne
        self._crashed = False
        self._failsafe: str | None = None
        self._failsafe_since = 0.0
        self._armed_since = now
        self._stream: deque[float] = deque()
        self._last_setpoint_time = -math.inf
        self._sp = (0.0, 0.0, 0.0, 0.0)
        self._sp_body = False
        self._sp_yaw: float | None = None
        self._sample: VehicleSample | None = None
        self._low_since: float | None = None  # land detector: conditions hold since
        self._takeoff_base = 0.0  # z where the climb started
        self._takeoff_target = 0.0
        self._events: list[CommanderEvent] = []

    @property
    def state(self) -> State:
        return self._state

    @property
    def armed(self) -> bool:
        return self._state != State.DISARMED

    @property
    def landed(self) -> bool:
        """The land detector's verdict (True after a reset on the ground)."""
        return self._landed

    @property
    def failsafe(self) -> bool:
        """True while a failsafe action (hold after setpoint loss, its landing) runs."""
        return self._failsafe is not None

    @property
    def failsafe_reason(self) -> str | None:
        return self._failsafe

    @property
    def crashed(self) -> bool:
        return self._crashed

    def pop_events(self) -> list[CommanderEvent]:
        """Events since the last call, oldest first."""
        events, self._events = self._events, []
        return events

    # ------------------------------------------------------------------ setpoints
    def setpoint(self, now: float, vx: float, vy: float, vz: float, yaw_rate: float, *,
                 body: bool = False, yaw: float | None = None) -> bool:
        """Offer a velocity setpoint (ENU world, or FLU body-horizontal if ``body``;
        ``yaw``: an absolute ENU heading target that replaces ``yaw_rate``).
        Non-finite values are refused (False, counted) and change nothing."""
        values = (vx, vy, vz, yaw_rate) + (() if yaw is None else (yaw,))
        if not all(math.isfinite(v) for v in values):
            self.rejected_setpoints += 1
            return False
        self._sp = (float(vx), float(vy), float(vz), float(yaw_rate))
        self._sp_body = bool(body)
        self._sp_yaw = None if yaw is None else float(yaw)
        self._last_setpoint_time = now
        self._stream.append(now)
        self._trim_stream(now)
        return True

    def _trim_stream(self, now: float) -> None:
        while self._stream and self._stream[0] <= now - self.config.stream_window + EPS:
            self._stream.popleft()

    def streaming(self, now: float) -> bool:
        """True if setpoints arrive faster than ``stream_min_rate`` (see module doc)."""
        c = self.config
        self._trim_stream(now)
        fresh = now - self._last_setpoint_time <= 1.0 / c.stream_min_rate + EPS
        return fresh and len(self._stream) > c.stream_min_rate * c.stream_window + EPS

    # ------------------------------------------------------------------ requests
    def arm(self, now: float) -> Verdict:
        """Arm on the ground. Already armed: accepted. Refused after a collision
        (``invalid_state``) or when the land detector says airborne (``not_landed``)."""
        if self.armed:
            return ACCEPTED
        if self._crashed:
            return self._refuse(now, "invalid_state", "Arming denied: crashed, reset first")
        if not self._landed:
            return self._refuse(now, "not_landed", "Arming denied: not landed")
        self._armed_since = now
        self._go(now, State.ARMED, "Armed")
        return ACCEPTED

    def disarm(self, now: float, force: bool = False) -> Verdict:
        """Disarm when landed (``force``: also in the air, as PX4's 21196)."""
        if not self.armed:
            return ACCEPTED
        if not (self._landed or force):
            return self._refuse(now, "in_air", "Disarming denied: in air")
        self._go(now, State.DISARMED, "Disarmed" + (" (forced)" if not self._landed else ""))
        return ACCEPTED

    def takeoff(self, now: float, altitude: float | None = None) -> Verdict:
        """Climb ``altitude`` m (None or NaN: ``takeoff_altitude``) above here, then hold."""
        c = self.config
        if altitude is None or math.isnan(altitude):
            altitude = c.takeoff_altitude
        if not (math.isfinite(altitude) and 0.0 < altitude <= c.max_takeoff_altitude):
            return self._refuse(now, "bad_altitude", "Takeoff denied: bad altitude")
        if self._state == State.DISARMED:
            return self._refuse(now, "not_armed", "Takeoff denied: not armed")
        if self._state not in (State.ARMED, State.TAKEOFF):
            return self._refuse(now, "invalid_state", "Takeoff denied: already flying")
        if self._state == State.ARMED:
            self._takeoff_base = self._sample.z if self._sample is not None else 0.0
            self._go(now, State.TAKEOFF, f"Takeoff to {altitude:.1f} m")
        self._takeoff_target = self._takeoff_base + altitude  # TAKEOFF: a new target
        return ACCEPTED

    def land(self, now: float) -> Verdict:
        """Descend, touch down, disarm."""
        if not self.armed:
            return self._refuse(now, "not_armed", "Land denied: not armed")
        if self._state != State.LAND:
            self._failsafe = None
            self._go(now, State.LAND, "Landing")
        return ACCEPTED

    def set_mode(self, now: float, state: str) -> Verdict:
        """Switch to ``"OFFBOARD"``, ``"HOLD"``, ``"LAND"`` or ``"TAKEOFF"``.

        On the ground HOLD (and LAND while disarmed) is accepted and changes nothing:
        that is what the vehicle already reports. OFFBOARD needs the vehicle armed and
        setpoints streaming. Anything else (RTL, unknown names) is ``unsupported_mode``.
        """
        if state == State.TAKEOFF:
            return self.takeoff(now)
        if state == State.LAND:
            return ACCEPTED if not self.armed else self.land(now)
        if state == State.HOLD:
            if self._state in (State.DISARMED, State.ARMED):
                return ACCEPTED
            self._failsafe = None
            if self._state != State.HOLD:
                self._go(now, State.HOLD, "Hold")
            return ACCEPTED
        if state == State.OFFBOARD:
            if not self.armed:
                return self._refuse(now, "not_armed", "Offboard denied: not armed")
            if not self.streaming(now):
                return self._refuse(now, "no_setpoint_stream", "Offboard denied: no setpoints")
            self._failsafe = None
            if self._state != State.OFFBOARD:
                self._go(now, State.OFFBOARD, "Offboard")
            return ACCEPTED
        return self._refuse(now, "unsupported_mode", f"Mode {state!s:.20} not supported")

    def collision(self, now: float) -> None:
        """A collision: disarm at once, report it, refuse arming until :meth:`reset`."""
        self._crashed = True
        self._failsafe = None
        self._state = State.DISARMED
        self._events.append(CommanderEvent(now, "collision", "Collision: disarmed",
                                           "critical", self._state))

    # ------------------------------------------------------------------ control step
    def step(self, now: float, sample: VehicleSample) -> Setpoint:
        """Advance to ``now`` with the vehicle's state; return the setpoint to fly."""
        c = self.config
        self._sample = sample
        self._detect_landing(now, sample)
        s = self._state
        if s == State.OFFBOARD:
            if now - self._last_setpoint_time > c.setpoint_timeout + EPS:
                self._failsafe, self._failsafe_since = "setpoint_loss", now
                self._go(now, State.HOLD, "Failsafe: setpoints lost, holding",
                         kind="failsafe", severity="critical")
                return ZERO
            return self._offboard_setpoint(sample.yaw)
        if s == State.HOLD:
            if self._failsafe is not None and now - self._failsafe_since >= \
                    c.hold_before_land - EPS:
                self._go(now, State.LAND, "Failsafe: landing", kind="failsafe",
                         severity="critical")
                return Setpoint(0.0, 0.0, -c.land_speed, 0.0)
            return ZERO
        if s == State.TAKEOFF:
            error = self._takeoff_target - sample.z
            if error <= c.takeoff_tolerance:
                self._go(now, State.HOLD, "Takeoff complete, holding")
                return ZERO
            return Setpoint(0.0, 0.0, min(c.takeoff_speed, c.takeoff_gain * error), 0.0)
        if s == State.LAND:
            if self._landed:
                self._failsafe = None
                self._go(now, State.DISARMED, "Landed, disarmed")
                return ZERO
            return Setpoint(0.0, 0.0, -c.land_speed, 0.0)
        if s == State.ARMED and now - self._armed_since >= c.disarm_preflight - EPS \
                and c.disarm_preflight > 0.0:
            self._go(now, State.DISARMED, "Disarmed: no takeoff")
        return ZERO

    def _offboard_setpoint(self, yaw: float) -> Setpoint:
        vx, vy, vz, yaw_rate = self._sp
        if self._sp_body:  # as sitl.episode.body_to_world, operation for operation
            cy, sy = math.cos(yaw), math.sin(yaw)
            vx, vy = cy * vx - sy * vy, sy * vx + cy * vy
        if self._sp_yaw is not None:
            c = self.config
            err = (self._sp_yaw - yaw + math.pi) % (2.0 * math.pi) - math.pi
            yaw_rate = max(-c.max_yaw_rate, min(c.max_yaw_rate, c.yaw_gain * err))
        return Setpoint(vx, vy, vz, yaw_rate)

    def _detect_landing(self, now: float, sample: VehicleSample) -> None:
        c = self.config
        low = sample.height_agl <= c.land_detect_height and abs(sample.vz) <= c.land_detect_speed
        if not low:
            self._low_since = None
            self._landed = False
            return
        if self._low_since is None:
            self._low_since = now
        if now - self._low_since >= c.land_detect_time - EPS:
            self._landed = True

    # ------------------------------------------------------------------ helpers
    def _go(self, now: float, state: State, text: str, kind: str = "mode",
            severity: str = "info") -> None:
        self._state = state
        self._events.append(CommanderEvent(now, kind, text, severity, state))

    def _refuse(self, now: float, reason: str, text: str) -> Verdict:
        self._events.append(CommanderEvent(now, "rejected", text, "warning", self._state))
        return Verdict(False, reason)
