"""Commander state machine: every transition, refusal reasons, failsafe timing to the step."""

from __future__ import annotations

import math

import pytest

from sitl.commander.machine import (
    Commander,
    CommanderConfig,
    Setpoint,
    State,
    VehicleSample,
    Verdict,
)

DT = 0.1


class Sim:
    """A point that flies the commander's vertical speed exactly; time = k * DT."""

    def __init__(self, commander: Commander, z: float = 0.0, yaw: float = 0.0) -> None:
        self.c = commander
        self.k = 0
        self.z = z
        self.vz = 0.0
        self.yaw = yaw
        self.out = Setpoint(0.0, 0.0, 0.0, 0.0)

    @property
    def now(self) -> float:
        return self.k * DT

    def step(self, n: int = 1, stream: tuple[float, float, float, float] | None = None,
             body: bool = False) -> Setpoint:
        for _ in range(n):
            self.k += 1
            if stream is not None:
                self.c.setpoint(self.now, *stream, body=body)
            self.out = self.c.step(self.now, VehicleSample(self.z, self.vz, self.yaw, self.z))
            self.vz = self.out.vz if self.c.armed else 0.0
            self.z = max(0.0, self.z + self.vz * DT)
            if self.z == 0.0:
                self.vz = max(0.0, self.vz)
        return self.out

    def stream(self, n: int, sp: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
               body: bool = False) -> Setpoint:
        return self.step(n, stream=sp, body=body)


def refused(v: Verdict, reason: str) -> bool:
    return not v.accepted and v.reason == reason


def airborne(config: CommanderConfig | None = None, z: float = 5.0) -> tuple[Commander, Sim]:
    c = Commander(config)
    c.reset(0.0, airborne=True)
    sim = Sim(c, z=z)
    sim.step()
    return c, sim


def in_offboard(config: CommanderConfig | None = None) -> tuple[Commander, Sim]:
    c, sim = airborne(config)
    sim.stream(5)
    assert c.set_mode(sim.now, "OFFBOARD").accepted
    return c, sim


# ------------------------------------------------------------------ arming
def test_arm_disarm_on_ground() -> None:
    c = Commander()
    sim = Sim(c)
    assert c.state == State.DISARMED and not c.armed and c.landed
    assert c.arm(0.0).accepted and c.state == State.ARMED
    assert c.arm(0.0).accepted  # already armed: accepted, no change
    assert c.disarm(0.1).accepted and c.state == State.DISARMED
    assert c.disarm(0.1).accepted
    sim.step()
    kinds = [(e.kind, e.state) for e in c.pop_events()]
    assert kinds == [("mode", State.ARMED), ("mode", State.DISARMED)]
    assert c.pop_events() == []


def test_arm_refused_when_not_landed_or_crashed() -> None:
    c, sim = airborne()
    assert refused(c.disarm(sim.now), "in_air") and c.armed
    assert c.disarm(sim.now, force=True).accepted and c.state == State.DISARMED
    assert refused(c.arm(sim.now), "not_landed")
    c = Commander()
    c.collision(1.0)
    assert c.crashed and c.state == State.DISARMED
    assert refused(c.arm(1.0), "invalid_state")
    assert [e.kind for e in c.pop_events()] == ["collision", "rejected"]
    c.reset(2.0)
    assert c.arm(2.0).accepted


def test_collision_disarms_in_flight() -> None:
    c, sim = in_offboard()
    c.collision(sim.now)
    assert c.state == State.DISARMED and not c.armed
    ev = c.pop_events()[-1]
    assert ev.kind == "collision" and ev.severity == "critical"
    assert sim.step() == (0.0, 0.0, 0.0, 0.0)


def test_preflight_auto_disarm() -> None:
    c = Commander(CommanderConfig(disarm_preflight=2.0))
    sim = Sim(c)
    sim.step()
    assert c.arm(sim.now).accepted  # at t = 0.1
    sim.step(19)  # t = 2.0: 1.9 s armed
    assert c.state == State.ARMED
    sim.step()  # t = 2.1: 2.0 s
    assert c.state == State.DISARMED


# ------------------------------------------------------------------ takeoff and land
def test_takeoff_refusals() -> None:
    for armed in (False, True):  # the same checks disarmed (a pending takeoff) and armed
        c = Commander()
        if armed:
            c.arm(0.0)
        for bad in (math.inf, -math.inf, -1.0, 0.0, 1000.0):
            assert refused(c.takeoff(0.0, bad), "bad_altitude")
        assert c.state == (State.ARMED if armed else State.DISARMED)
        assert c.pending_takeoff is None
    c, sim = airborne()
    assert refused(c.takeoff(sim.now, 3.0), "invalid_state")
    assert c.disarm(sim.now, force=True).accepted  # disarmed, falling: not landed
    assert refused(c.takeoff(sim.now, 3.0), "not_landed") and c.pending_takeoff is None
    c = Commander()
    c.collision(1.0)
    assert refused(c.takeoff(1.0, 3.0), "invalid_state") and c.state == State.DISARMED
    assert c.pop_events()[-1].text == "Takeoff denied: crashed"


# ------------------------------------------------------------------ takeoff while disarmed
def pending(altitude: float = 3.0) -> tuple[Commander, Sim]:
    """QGroundControl's Takeoff, first half: NAV_TAKEOFF while disarmed on the ground."""
    c = Commander()
    sim = Sim(c)
    sim.step()
    assert c.takeoff(sim.now, altitude).accepted
    return c, sim


def test_takeoff_while_disarmed_is_pending_and_reported_as_takeoff() -> None:
    c, sim = pending(3.0)
    assert c.state == State.TAKEOFF and not c.armed and c.pending_takeoff == 3.0
    ev = c.pop_events()
    assert [(e.kind, e.text, e.state) for e in ev] == \
        [("mode", "Takeoff pending: 3.0 m, arm to start", State.TAKEOFF)]
    sim.step(600)  # a minute: no climb (motors off), no expiry (as PX4)
    assert sim.z == 0.0 and c.state == State.TAKEOFF and c.pending_takeoff == 3.0
    assert c.pop_events() == []
    assert c.takeoff(sim.now, 4.0).accepted and c.pending_takeoff == 4.0  # a new altitude
    assert c.takeoff(sim.now, math.nan).accepted and c.pending_takeoff == 2.5  # default


def test_arming_with_a_pending_takeoff_climbs_to_its_altitude() -> None:
    c, sim = pending(3.0)
    assert c.arm(sim.now).accepted
    assert c.state == State.TAKEOFF and c.armed and c.pending_takeoff is None
    assert sim.step() == (0.0, 0.0, 1.5, 0.0)
    for _ in range(300):  # well past disarm_preflight (10 s): it is flying, not idle
        if c.state != State.TAKEOFF:
            break
        sim.step()
    assert c.state == State.HOLD and 2.9 <= sim.z <= 3.0
    assert [e.text for e in c.pop_events()] == ["Takeoff pending: 3.0 m, arm to start",
                                                "Armed", "Takeoff to 3.0 m",
                                                "Takeoff complete, holding"]


@pytest.mark.parametrize("cancel", ["disarm", "HOLD", "LAND"])
def test_disarm_hold_or_land_cancels_a_pending_takeoff(cancel: str) -> None:
    c, sim = pending()
    c.pop_events()
    v = c.disarm(sim.now) if cancel == "disarm" else c.set_mode(sim.now, cancel)
    assert v.accepted and c.state == State.DISARMED and c.pending_takeoff is None
    assert [(e.text, e.state) for e in c.pop_events()] == \
        [("Takeoff cancelled", State.DISARMED)]
    assert c.arm(sim.now).accepted and c.state == State.ARMED  # arming: no climb
    sim.step(5)
    assert sim.z == 0.0 and c.state == State.ARMED


def test_refused_requests_keep_a_pending_takeoff_and_collision_place_reset_clear_it() -> None:
    c, sim = pending()
    for mode in ("OFFBOARD", "RTL", "ACRO"):
        assert not c.set_mode(sim.now, mode).accepted
    assert not c.land(sim.now).accepted
    assert c.state == State.TAKEOFF and c.pending_takeoff == 3.0
    c.collision(sim.now)
    assert c.state == State.DISARMED and c.pending_takeoff is None
    for clear in (lambda: c.place(sim.now, airborne=False), lambda: c.reset(sim.now)):
        c.reset(sim.now)
        assert c.takeoff(sim.now, 3.0).accepted and c.state == State.TAKEOFF
        clear()
        assert c.state == State.DISARMED and c.pending_takeoff is None


def test_auto_disarm_and_failsafes_unchanged_by_a_takeoff_that_was_pending() -> None:
    """Preflight auto-disarm still applies to an armed idle vehicle (no pending takeoff
    survives it), and a takeoff that was pending flies the same failsafes."""
    c = Commander(CommanderConfig(disarm_preflight=2.0))
    sim = Sim(c)
    sim.step()
    c.arm(sim.now)
    sim.step(20)
    assert c.state == State.DISARMED and c.pending_takeoff is None
    assert c.takeoff(sim.now, 2.0).accepted and c.arm(sim.now).accepted
    for _ in range(100):
        if c.state != State.TAKEOFF:
            break
        sim.step()
    assert c.state == State.HOLD and not c.landed
    sim.stream(2)
    assert c.set_mode(sim.now, "OFFBOARD").accepted
    sim.step(11)  # setpoints lost for > 1 s
    assert c.state == State.HOLD and c.failsafe_reason == "setpoint_loss"


def test_takeoff_climbs_then_holds() -> None:
    c = Commander()
    sim = Sim(c, z=0.0)
    sim.step()
    c.arm(sim.now)
    assert c.takeoff(sim.now, math.nan).accepted  # NaN: the default 2.5 m
    assert c.state == State.TAKEOFF and c.takeoff(sim.now, 2.5).accepted
    assert sim.step() == (0.0, 0.0, 1.5, 0.0)  # capped at takeoff_speed
    for _ in range(200):
        if c.state != State.TAKEOFF:
            break
        out = sim.step()
        assert 0.0 <= out.vz <= 1.5
    assert c.state == State.HOLD and 2.4 <= sim.z <= 2.5
    assert not c.landed and sim.step() == (0.0, 0.0, 0.0, 0.0)
    texts = [e.text for e in c.pop_events()]
    assert texts == ["Armed", "Takeoff to 2.5 m", "Takeoff complete, holding"]


def test_land_touches_down_and_disarms() -> None:
    c, sim = airborne(z=1.0)
    assert c.land(sim.now).accepted and c.state == State.LAND
    assert sim.step() == (0.0, 0.0, -0.7, 0.0)
    sim.step(15)  # 1.0 m at 0.7 m/s: on the ground after ~1.5 s
    assert sim.z == 0.0 and c.state == State.LAND  # land detector needs 0.5 s
    sim.step(6)
    assert c.state == State.DISARMED and c.landed
    assert c.pop_events()[-1].text == "Landed, disarmed"
    assert refused(c.land(sim.now), "not_armed")


def test_land_on_the_ground_disarms_at_once() -> None:
    c = Commander()
    sim = Sim(c)
    c.arm(0.0)
    assert c.land(0.0).accepted
    sim.step()
    assert c.state == State.DISARMED


def test_modes_on_the_ground_are_accepted_noops_or_refused() -> None:
    c = Commander()
    assert c.set_mode(0.0, "HOLD").accepted and c.state == State.DISARMED
    assert c.set_mode(0.0, "LAND").accepted and c.state == State.DISARMED
    assert c.disarm(0.0).accepted and c.pop_events() == []  # no-ops: nothing reported
    assert refused(c.set_mode(0.0, "OFFBOARD"), "not_armed")
    assert refused(c.set_mode(0.0, "RTL"), "not_armed")
    assert refused(c.set_mode(0.0, "ACRO"), "unsupported_mode")
    c.arm(0.0)
    assert c.set_mode(0.0, "HOLD").accepted and c.state == State.ARMED
    assert c.set_mode(0.0, "TAKEOFF").accepted and c.state == State.TAKEOFF


# ------------------------------------------------------------------ offboard
def test_offboard_needs_a_recent_setpoint() -> None:
    """PX4's check: one setpoint no older than COM_OF_LOSS_T; none or a stale one: no."""
    c, sim = airborne(CommanderConfig(setpoint_timeout=1.0))
    assert refused(c.set_mode(sim.now, "OFFBOARD"), "no_setpoint_stream")  # none yet
    assert not c.offboard_available(sim.now)
    sim.stream(1)  # a single setpoint, as MAVSDK's set_velocity_* then start()
    assert c.offboard_available(sim.now)
    sim.step(10)  # the newest exactly 1.0 s old: still available (not lost)
    assert c.offboard_available(sim.now)
    sim.step(1)  # 1.1 s old: stale
    assert refused(c.set_mode(sim.now, "OFFBOARD"), "no_setpoint_stream")
    assert c.state == State.HOLD and c.pop_events()[-1].text == "Offboard denied: no setpoints"
    sim.stream(1)
    assert c.set_mode(sim.now, "OFFBOARD").accepted and c.state == State.OFFBOARD


def test_offboard_accepted_at_the_same_instant_as_the_first_setpoint() -> None:
    c, sim = airborne()
    assert c.setpoint(sim.now, 1.0, 0.0, 0.0, 0.0)
    assert c.set_mode(sim.now, "OFFBOARD").accepted
    assert sim.step() == (1.0, 0.0, 0.0, 0.0)


def test_offboard_availability_follows_com_of_loss_t() -> None:
    c, sim = airborne(CommanderConfig(setpoint_timeout=0.5))
    sim.stream(1)
    sim.step(6)  # 0.6 s > 0.5 s
    assert refused(c.set_mode(sim.now, "OFFBOARD"), "no_setpoint_stream")
    c.config.setpoint_timeout = 2.0  # COM_OF_LOSS_T raised (vehicle_service.apply_param)
    assert c.set_mode(sim.now, "OFFBOARD").accepted


def test_offboard_flies_setpoints_in_world_and_body_frames() -> None:
    c, sim = in_offboard()
    assert sim.stream(1, (1.0, -2.0, 0.5, 0.3)) == (1.0, -2.0, 0.5, 0.3)
    sim.yaw = math.pi / 2  # facing north: forward = north, left = west
    out = sim.stream(1, (1.0, 0.5, 0.0, -0.2), body=True)
    assert out == pytest.approx((-0.5, 1.0, 0.0, -0.2))
    assert c.setpoint(sim.now, 0.0, 0.0, 0.0, 0.0, yaw=0.0)  # heading target east
    out = sim.step()
    assert out.yaw_rate == pytest.approx(-math.pi / 2 * 1.0)  # gain 1, clockwise
    c.setpoint(sim.now, 0.0, 0.0, 0.0, 0.0, yaw=-math.pi / 2)  # half a turn: clamped
    assert sim.step().yaw_rate == -c.config.max_yaw_rate


def test_non_finite_setpoints_are_refused_and_counted() -> None:
    c, sim = in_offboard()
    sim.stream(1, (1.0, 0.0, 0.0, 0.0))
    t_last = sim.now
    sim.step()
    for bad in ((math.nan, 0.0, 0.0, 0.0), (0.0, math.inf, 0.0, 0.0), (0.0, 0.0, 0.0, -math.inf)):
        assert not c.setpoint(sim.now, *bad)
    assert not c.setpoint(sim.now, 0.0, 0.0, 0.0, 0.0, yaw=math.nan)
    assert c.rejected_setpoints == 4
    assert c.last_setpoint_time == t_last  # a refused setpoint is not a setpoint
    assert sim.step() == (1.0, 0.0, 0.0, 0.0)


def test_setpoint_loss_failsafe_timing() -> None:
    cfg = CommanderConfig(setpoint_timeout=1.0, hold_before_land=5.0)
    c, sim = in_offboard(cfg)
    sim.stream(14, (1.0, 0.0, 0.0, 0.0))
    t_last = sim.now
    assert c.last_setpoint_time == t_last  # what loss is counted from (and published)
    sim.step(10)  # newest setpoint exactly 1.0 s old: still offboard
    assert sim.now - t_last == pytest.approx(1.0) and c.state == State.OFFBOARD
    assert sim.out == (1.0, 0.0, 0.0, 0.0)
    sim.step()  # 1.1 s: lost
    assert c.state == State.HOLD and c.failsafe and c.failsafe_reason == "setpoint_loss"
    assert sim.out == (0.0, 0.0, 0.0, 0.0)
    t_hold = sim.now
    ev = c.pop_events()[-1]
    assert (ev.kind, ev.severity, ev.time) == ("failsafe", "critical", t_hold)
    sim.stream(49)  # setpoints are back: no automatic return to offboard
    assert sim.now - t_hold == pytest.approx(4.9) and c.state == State.HOLD
    sim.step()  # 5.0 s in hold
    assert c.state == State.LAND and c.failsafe and sim.out.vz == -0.7
    assert c.pop_events()[-1].text == "Failsafe: landing"
    sim.step(200)
    assert c.state == State.DISARMED and not c.failsafe


def test_failsafe_hold_ends_when_offboard_is_asked_again() -> None:
    c, sim = in_offboard()
    sim.step(11)
    assert c.state == State.HOLD and c.failsafe
    sim.stream(3)
    assert c.set_mode(sim.now, "OFFBOARD").accepted
    assert c.state == State.OFFBOARD and not c.failsafe
    sim.stream(100)
    assert c.state == State.OFFBOARD


def test_manual_hold_never_lands() -> None:
    c, sim = in_offboard()
    assert c.set_mode(sim.now, "HOLD").accepted and not c.failsafe
    sim.step(200)
    assert c.state == State.HOLD


def test_hold_before_land_infinite() -> None:
    c, sim = in_offboard(CommanderConfig(hold_before_land=math.inf))
    sim.step(300)
    assert c.state == State.HOLD and c.failsafe


def test_offboard_from_armed_on_ground_and_land_mode_in_air() -> None:
    c = Commander()
    sim = Sim(c)
    c.arm(0.0)
    sim.stream(3, (0.0, 0.0, 1.0, 0.0))
    assert c.set_mode(sim.now, "OFFBOARD").accepted
    sim.stream(10, (0.0, 0.0, 1.0, 0.0))
    assert sim.z == pytest.approx(1.0) and not c.landed
    assert c.set_mode(sim.now, "LAND").accepted and c.state == State.LAND
    assert c.set_mode(sim.now, "HOLD").accepted and c.state == State.HOLD  # abort landing
    assert refused(c.set_mode(sim.now, "TAKEOFF"), "invalid_state")


def test_takeoff_before_the_first_step_climbs_from_where_the_vehicle_is() -> None:
    """A request served before the commander's first step (the sim's first control
    step): the base is the first sample's height, not 0."""
    c = Commander()
    assert c.arm(0.0).accepted and c.takeoff(0.0, 2.0).accepted  # no sample yet
    sim = Sim(c, z=0.5)
    for _ in range(200):
        if c.state != State.TAKEOFF:
            break
        sim.step()
    assert c.state == State.HOLD and 2.4 <= sim.z <= 2.5


def test_takeoff_can_be_interrupted_by_offboard_or_land() -> None:
    for target in ("OFFBOARD", "LAND"):
        c = Commander()
        sim = Sim(c)
        c.arm(0.0)
        c.takeoff(0.0, 5.0)
        sim.stream(10, (0.0, 0.0, 0.5, 0.0))  # 1 s into the climb, setpoints streaming
        assert c.state == State.TAKEOFF and sim.z > 1.0
        assert c.set_mode(sim.now, target).accepted and c.state == target
        out = sim.stream(1, (0.0, 0.0, 0.5, 0.0))
        assert out.vz == (0.5 if target == "OFFBOARD" else -0.7)
