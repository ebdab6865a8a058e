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
    DISARMED --takeoff (landed)--> DISARMED, takeoff pending --arm--> TAKEOFF
    ARMED/TAKEOFF/HOLD/LAND --set_mode OFFBOARD (a recent setpoint)--> OFFBOARD
    OFFBOARD --no setpoint for setpoint_timeout--> HOLD (failsafe)
    HOLD (failsafe) --hold_before_land--> LAND --touchdown--> DISARMED
    any in-air state --land / set_mode HOLD / set_mode RTL--> LAND / HOLD / RTL
    TAKEOFF/OFFBOARD/HOLD --beyond the geofence--> RTL (failsafe)
    RTL --climb, return, descend, touchdown--> DISARMED
    ARMED --disarm_preflight without takeoff--> DISARMED;  any --collision--> DISARMED

* OFFBOARD is accepted only while offboard control is *available*, PX4's check
  (``offboardCheck``): the newest setpoint is no older than ``setpoint_timeout``
  (COM_OF_LOSS_T, the loss failsafe's threshold, so "available" is exactly "not lost").
  One recent setpoint is enough, as MAVSDK's "set a setpoint, then ``offboard.start()``"
  expects; none, or only stale ones: ``no_setpoint_stream``. Staying in OFFBOARD takes
  a setpoint at least every ``setpoint_timeout``.
* Setpoint loss: at the first :meth:`step` where the newest setpoint is older than
  ``setpoint_timeout`` (strictly, with a 1 ns tolerance for float time), OFFBOARD falls
  to HOLD (a failsafe); at the first step ``hold_before_land`` seconds after that, to
  LAND (``math.inf``: hold forever). Setpoints coming back do not resume OFFBOARD by
  themselves (as PX4): the client asks for OFFBOARD again, which ends the failsafe.
* Setpoints are always recorded (so one can be offered before the switch) but flown
  only in OFFBOARD: body-frame ones rotated by the current yaw, heading targets turned
  into yaw rates (:func:`sitl.commander.guidance.offboard_setpoint`).
* Takeoff climbs to ``altitude`` (default ``takeoff_altitude``) above the height where
  the climb starts (the next :meth:`step`'s if none came before), at
  ``min(takeoff_speed, takeoff_gain * error)``, then holds. LAND descends at
  ``land_speed``; touchdown is the land detector (height above ground and vertical
  speed under thresholds for ``land_detect_time``), then it disarms.
* Takeoff while disarmed on the ground (PX4 switches to AUTO.TAKEOFF disarmed;
  QGroundControl's Takeoff sends NAV_TAKEOFF first and arms once it is accepted) leaves
  a *pending* takeoff: :attr:`~Commander.state` reports TAKEOFF, :attr:`~Commander.armed`
  False; arming starts the climb at once (so ``disarm_preflight``, which applies to
  ARMED only, never sees it). Disarm, HOLD or LAND requests (accepted no-ops otherwise),
  a collision, :meth:`~Commander.place` and :meth:`~Commander.reset` cancel it; refused
  requests and time do not (PX4 also waits for arming as long as it takes). Refused
  disarmed as arming is: crashed (``invalid_state``), not landed (``not_landed``).
* A collision disarms, is reported, and latches: arming is refused until :meth:`reset`.
* Home is where the vehicle armed (or where :meth:`~Commander.place` put it). RTL climbs
  to ``flight_level`` above the ground (or keeps its height if already higher) at
  ``rtl_climb_speed``, flies straight to home at ``rtl_speed`` holding that altitude
  (slowing as ``rtl_gain * distance`` within the last metres), descends at
  ``land_speed`` once within ``rtl_arrive_radius``, touches down and disarms.
* Geofence: in TAKEOFF, OFFBOARD or HOLD, a horizontal distance from home beyond
  ``geofence`` (> 0) starts RTL as a failsafe (``failsafe_reason`` ``"geofence"``).
* :meth:`~Commander.place`: the vehicle was moved (a simulator episode reset): the land
  detector restarts, the collision latch clears, home becomes the new position, and the
  commander continues airborne in the mode it is given (OFFBOARD keeps its stream).

Verdict reasons: ``not_landed``, ``invalid_state``, ``not_armed``, ``in_air``,
``bad_altitude``, ``no_setpoint_stream``, ``unsupported_mode``, ``landed``.
"""

from __future__ import annotations

import math

from sitl.commander.guidance import detect_landing, offboard_setpoint, rtl_setpoint
from sitl.commander.types import (
    ACCEPTED,
    EPS,
    ZERO,
    CommanderConfig,
    CommanderEvent,
    Setpoint,
    State,
    VehicleSample,
    Verdict,
)

__all__ = ["ACCEPTED", "EPS", "ZERO", "Commander", "CommanderConfig",
           "CommanderEvent", "Setpoint", "State", "VehicleSample", "Verdict"]  # re-exported

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
        self._last_setpoint_time = -math.inf
        self._offboard_asked = -math.inf
        self._sp = (0.0, 0.0, 0.0, 0.0)
        self._sp_body = False
        self._sp_yaw: float | None = None
        self._sample: VehicleSample | None = None
        self._low_since: float | None = None  # land detector: conditions hold since
        self._takeoff_base: float | None = 0.0  # z where the climb started (None: next step's)
        self._takeoff_alt = 0.0  # m above the base
        self._pending: float | None = None  # m, a takeoff accepted disarmed (flown at arming)
        self._home: tuple[float, float] | None = None  # (x, y) where it armed
        self._rehome = False  # take home from the next sample
        self._rtl_z = 0.0  # altitude of the return leg
        self._rtl_phase = "climb"  # climb, return, descend
        self._events: list[CommanderEvent] = []

    def place(self, now: float, airborne: bool, mode: State | str = State.HOLD) -> None:
        """The vehicle was moved (see the module docstring): ``airborne`` -> armed in
        ``mode`` (OFFBOARD or HOLD; anything else -> HOLD), else disarmed on the ground.
        Setpoint history is kept, so an OFFBOARD stream carries on across the move."""
        self._crashed = False
        self._failsafe = None
        self._pending = None
        self._low_since = None
        self._landed = not airborne
        self._rehome = True
        self._armed_since = now
        if not airborne:
            self._state = State.DISARMED
        else:
            self._state = State.OFFBOARD if mode == State.OFFBOARD else State.HOLD

    @property
    def home(self) -> tuple[float, float] | None:
        """Horizontal home position (where it armed or was placed), None before."""
        return self._home

    @property
    def state(self) -> State:
        """The mode: TAKEOFF while a takeoff waits for arming (disarmed), else the state."""
        return State.TAKEOFF if self._pending is not None else self._state

    @property
    def pending_takeoff(self) -> float | None:
        """Metres of a takeoff accepted disarmed, flown once armed (None: none)."""
        return self._pending

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
        return True

    @property
    def last_setpoint_time(self) -> float:
        """When the newest accepted setpoint was offered (commander time; -inf: none
        since the last reset): what setpoint loss is counted from."""
        return self._last_setpoint_time

    @property
    def offboard_asked(self) -> float:
        """When OFFBOARD was last asked for and granted (commander time; -inf: never; an
        ask while in OFFBOARD counts too: a restarted companion asks once it flies)."""
        return self._offboard_asked

    def offboard_available(self, now: float) -> bool:
        """True if the newest setpoint is no older than ``setpoint_timeout`` (see the
        module docstring): what OFFBOARD needs, the negation of setpoint loss."""
        return now - self._last_setpoint_time <= self.config.setpoint_timeout + EPS

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
        self._rehome = True
        self._go(now, State.ARMED, "Armed")
        if self._pending is not None:
            altitude, self._pending = self._pending, None
            self._climb(now, altitude)
        return ACCEPTED

    def disarm(self, now: float, force: bool = False) -> Verdict:
        """Disarm when landed (``force``: also in the air, as PX4's 21196)."""
        if not self.armed:
            return self._cancel_pending(now)
        if not (self._landed or force):
            return self._refuse(now, "in_air", "Disarming denied: in air")
        self._go(now, State.DISARMED, "Disarmed" + (" (forced)" if not self._landed else ""))
        return ACCEPTED

    def takeoff(self, now: float, altitude: float | None = None) -> Verdict:
        """Climb ``altitude`` m (None or NaN: ``takeoff_altitude``) above here, then hold;
        disarmed on the ground: once armed (a pending takeoff, see the module docstring)."""
        c = self.config
        if altitude is None or math.isnan(altitude):
            altitude = c.takeoff_altitude
        if not (math.isfinite(altitude) and 0.0 < altitude <= c.max_takeoff_altitude):
            return self._refuse(now, "bad_altitude", "Takeoff denied: bad altitude")
        if self._state == State.DISARMED:
            if self._crashed:
                return self._refuse(now, "invalid_state", "Takeoff denied: crashed")
            if not self._landed:
                return self._refuse(now, "not_landed", "Takeoff denied: not landed")
            self._pending = altitude
            self._events.append(CommanderEvent(
                now, "mode", f"Takeoff pending: {altitude:.1f} m, arm to start", "info",
                State.TAKEOFF))
        elif self._state == State.ARMED:
            self._climb(now, altitude)
        elif self._state == State.TAKEOFF:
            self._takeoff_alt = altitude  # a new target above the same base
        else:
            return self._refuse(now, "invalid_state", "Takeoff denied: already flying")
        return ACCEPTED

    def land(self, now: float) -> Verdict:
        """Descend, touch down, disarm."""
        if not self.armed:
            return self._refuse(now, "not_armed", "Land denied: not armed")
        if self._state != State.LAND:
            self._failsafe = None
            self._go(now, State.LAND, "Landing")
        return ACCEPTED

    def return_home(self, now: float, reason: str | None = None) -> Verdict:
        """RTL (see the module docstring); ``reason``: a failsafe's name. Refused
        disarmed (``not_armed``) and on the ground (``landed``)."""
        if not self.armed:
            return self._refuse(now, "not_armed", "Return denied: not armed")
        if self._landed or self._state == State.ARMED:
            return self._refuse(now, "landed", "Return denied: landed")
        if self._state == State.RTL and reason is None:
            return ACCEPTED
        s = self._sample
        z, agl = (s.z, s.height_agl) if s is not None else (0.0, 0.0)
        self._rtl_z = z + max(0.0, self.config.flight_level - agl)
        self._rtl_phase = "climb"
        self._failsafe = reason
        if reason is None:
            self._go(now, State.RTL, "Returning home")
        else:
            self._failsafe_since = now
            self._go(now, State.RTL, f"Failsafe: {reason}, returning home", kind="failsafe",
                     severity="critical")
        return ACCEPTED

    def set_mode(self, now: float, state: str) -> Verdict:
        """Switch to ``"OFFBOARD"``, ``"HOLD"``, ``"LAND"``, ``"TAKEOFF"`` or ``"RTL"``.

        On the ground HOLD (and LAND while disarmed) is accepted and changes nothing but a
        pending takeoff (cancelled). OFFBOARD needs the vehicle armed and a
        recent setpoint (:meth:`offboard_available`). Unknown names: ``unsupported_mode``.
        """
        if state == State.RTL:
            return self.return_home(now)
        if state == State.TAKEOFF:
            return self.takeoff(now)
        if state == State.LAND:
            return self._cancel_pending(now) if not self.armed else self.land(now)
        if state == State.HOLD:
            if self._state in (State.DISARMED, State.ARMED):
                return self._cancel_pending(now)
            self._failsafe = None
            if self._state != State.HOLD:
                self._go(now, State.HOLD, "Hold")
            return ACCEPTED
        if state == State.OFFBOARD:
            if not self.armed:
                return self._refuse(now, "not_armed", "Offboard denied: not armed")
            if not self.offboard_available(now):
                return self._refuse(now, "no_setpoint_stream", "Offboard denied: no setpoints")
            self._failsafe = None
            self._offboard_asked = now
            if self._state != State.OFFBOARD:
                self._go(now, State.OFFBOARD, "Offboard")
            return ACCEPTED
        return self._refuse(now, "unsupported_mode", f"Mode {state!s:.20} not supported")

    def collision(self, now: float) -> None:
        """A collision: disarm at once, report it, refuse arming until :meth:`reset`."""
        self._crashed = True
        self._failsafe = None
        self._pending = None
        self._state = State.DISARMED
        self._events.append(CommanderEvent(now, "collision", "Collision: disarmed",
                                           "critical", self._state))

    # ------------------------------------------------------------------ control step
    def step(self, now: float, sample: VehicleSample) -> Setpoint:
        """Advance to ``now`` with the vehicle's state; return the setpoint to fly."""
        c = self.config
        self._sample = sample
        if self._rehome or self._home is None:
            self._home, self._rehome = (sample.x, sample.y), False
        self._low_since, self._landed = detect_landing(c, self._low_since, self._landed, now,
                                                       sample)
        s = self._state
        if s in (State.TAKEOFF, State.OFFBOARD, State.HOLD) and c.geofence > 0.0 and \
                math.hypot(sample.x - self._home[0], sample.y - self._home[1]) > c.geofence:
            self.return_home(now, "geofence")
            s = self._state
        if s == State.RTL:
            assert self._home is not None
            self._rtl_phase, out = rtl_setpoint(c, self._rtl_phase, self._rtl_z, self._home,
                                                sample, self._landed)
            if out is None:  # descended at home and touched down
                self._failsafe = None
                self._go(now, State.DISARMED, "Landed home, disarmed")
                return ZERO
            return out
        if s == State.OFFBOARD:
            if now - self._last_setpoint_time > c.setpoint_timeout + EPS:
                self._failsafe, self._failsafe_since = "setpoint_loss", now
                self._go(now, State.HOLD, "Failsafe: setpoints lost, holding",
                         kind="failsafe", severity="critical")
                return ZERO
            return offboard_setpoint(self._sp, self._sp_body, self._sp_yaw, sample.yaw, c)
        if s == State.HOLD:
            if self._failsafe is not None and now - self._failsafe_since >= \
                    c.hold_before_land - EPS:
                self._go(now, State.LAND, "Failsafe: landing", kind="failsafe",
                         severity="critical")
                return Setpoint(0.0, 0.0, -c.land_speed, 0.0)
            return ZERO
        if s == State.TAKEOFF:
            if self._takeoff_base is None:  # accepted before any step: the base is here
                self._takeoff_base = sample.z
            error = self._takeoff_base + self._takeoff_alt - sample.z
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

    # ------------------------------------------------------------------ helpers
    def _climb(self, now: float, altitude: float) -> None:
        """ARMED -> TAKEOFF: climb ``altitude`` above the latest sample's height."""
        self._takeoff_base = self._sample.z if self._sample is not None else None
        self._takeoff_alt = altitude
        self._go(now, State.TAKEOFF, f"Takeoff to {altitude:.1f} m")

    def _cancel_pending(self, now: float) -> Verdict:
        """Drop a pending takeoff (reported); accepted either way."""
        if self._pending is not None:
            self._pending = None
            self._go(now, State.DISARMED, "Takeoff cancelled")
        return ACCEPTED

    def _go(self, now: float, state: State, text: str, kind: str = "mode",
            severity: str = "info") -> None:
        self._state = state
        self._events.append(CommanderEvent(now, kind, text, severity, state))

    def _refuse(self, now: float, reason: str, text: str) -> Verdict:
        self._events.append(CommanderEvent(now, "rejected", text, "warning", self.state))
        return Verdict(False, reason)
