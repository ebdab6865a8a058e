"""Commander RTL and geofence: climb to the flight level, return home, descend, disarm."""

from __future__ import annotations

import math

from sitl.commander.machine import Commander, CommanderConfig, Setpoint, State, VehicleSample

DT = 0.1


class PointSim:
    """A point that flies the commander's ENU velocity exactly over flat ground at 0."""

    def __init__(self, commander: Commander, x: float = 0.0, y: float = 0.0,
                 z: float = 0.0) -> None:
        self.c, self.k = commander, 0
        self.x, self.y, self.z, self.vz = x, y, z, 0.0
        self.out = Setpoint(0.0, 0.0, 0.0, 0.0)
        self.states: list[State] = []

    @property
    def now(self) -> float:
        return self.k * DT

    def step(self, n: int = 1, stream: tuple[float, float, float, float] | None = None) -> None:
        for _ in range(n):
            self.k += 1
            if stream is not None:
                self.c.setpoint(self.now, *stream)
            self.out = self.c.step(self.now, VehicleSample(self.z, self.vz, 0.0, self.z,
                                                           self.x, self.y))
            if self.c.armed:
                self.x += self.out.vx * DT
                self.y += self.out.vy * DT
                self.vz = self.out.vz
            else:
                self.vz = 0.0
            self.z = max(0.0, self.z + self.vz * DT)
            if self.z == 0.0:
                self.vz = max(0.0, self.vz)
            if not self.states or self.states[-1] != self.c.state:
                self.states.append(self.c.state)


def flying(config: CommanderConfig | None = None) -> tuple[Commander, PointSim]:
    """Armed at (10, 20) on the ground, taken off to 2.5 m and in OFFBOARD."""
    c = Commander(config)
    sim = PointSim(c, 10.0, 20.0)
    sim.step()
    assert c.arm(sim.now).accepted and c.takeoff(sim.now).accepted
    sim.step(40)
    assert c.state == State.HOLD
    sim.step(5, stream=(0.0, 0.0, 0.0, 0.0))
    assert c.set_mode(sim.now, "OFFBOARD").accepted
    return c, sim


def test_rtl_climbs_returns_descends_and_disarms() -> None:
    c, sim = flying()
    assert c.home == (10.0, 20.0)
    sim.step(60, stream=(1.0, -0.5, 0.0, 0.0))  # fly away 6 m east, 3 m south
    assert math.hypot(sim.x - 10.0, sim.y - 20.0) > 5.0
    c.pop_events()
    assert c.set_mode(sim.now, "RTL").accepted and c.state == State.RTL
    assert not c.failsafe
    sim.step()
    assert sim.out.vz > 0.0 and sim.out.vx == sim.out.vy == 0.0  # climb first (2.5 < 3.5 m)
    for _ in range(400):
        sim.step()
        if c.state != State.RTL:
            break
    assert c.state == State.DISARMED and c.landed
    assert math.hypot(sim.x - 10.0, sim.y - 20.0) <= 0.5
    assert sim.z == 0.0
    texts = [e.text for e in c.pop_events()]
    assert texts[0] == "Returning home" and texts[-1] == "Landed home, disarmed"


def test_rtl_keeps_a_higher_altitude_and_caps_the_speed() -> None:
    c, sim = flying(CommanderConfig(rtl_speed=1.0))
    sim.step(30, stream=(0.0, 0.0, 2.0, 0.0))  # climb to ~8.5 m
    sim.step(50, stream=(2.0, 0.0, 0.0, 0.0))  # 10 m east
    z0 = sim.z
    c.set_mode(sim.now, "RTL")
    sim.step(3)
    assert sim.out.vz == 0.0 and abs(sim.out.vx + 1.0) < 1e-12  # straight back at 1 m/s
    assert sim.z == z0


def test_rtl_refused_on_the_ground() -> None:
    c = Commander()
    sim = PointSim(c)
    sim.step()
    assert c.set_mode(sim.now, "RTL").reason == "not_armed"
    c.arm(sim.now)
    assert c.set_mode(sim.now, "RTL").reason == "landed"
    assert c.state == State.ARMED


def test_geofence_breach_starts_rtl_failsafe() -> None:
    c, sim = flying(CommanderConfig(geofence=5.0))
    c.pop_events()
    for _ in range(100):
        sim.step(stream=(2.0, 0.0, 0.0, 0.0))
        if c.state != State.OFFBOARD:
            break
    assert c.state == State.RTL and c.failsafe and c.failsafe_reason == "geofence"
    assert 5.0 < sim.x - 10.0 <= 5.0 + 2.0 * DT + 1e-9  # the first step beyond the fence
    events = c.pop_events()
    assert [e.kind for e in events] == ["failsafe"]
    assert "geofence" in events[0].text
    for _ in range(400):
        sim.step(stream=(2.0, 0.0, 0.0, 0.0))  # setpoints no longer flown
        if c.state == State.DISARMED:
            break
    assert c.state == State.DISARMED and math.hypot(sim.x - 10.0, sim.y - 20.0) <= 0.5


def test_geofence_off_and_place_rehomes() -> None:
    c, sim = flying(CommanderConfig(geofence=0.0))
    sim.step(100, stream=(2.0, 0.0, 0.0, 0.0))
    assert c.state == State.OFFBOARD and sim.x - 10.0 > 19.0
    c.config.geofence = 5.0
    c.place(sim.now, airborne=True, mode=State.OFFBOARD)
    sim.step(stream=(0.0, 0.0, 0.0, 0.0))
    assert c.state == State.OFFBOARD and c.home == (sim.x, sim.y)  # home moved with it
    assert not c.crashed and not c.landed


def test_place_after_collision_clears_the_latch() -> None:
    c, sim = flying()
    c.collision(sim.now)
    assert c.crashed and c.state == State.DISARMED
    c.place(sim.now, airborne=True, mode="OFFBOARD")
    assert c.state == State.OFFBOARD and c.armed and not c.crashed
    c.place(sim.now, airborne=False)
    assert c.state == State.DISARMED and c.landed and c.arm(sim.now).accepted
