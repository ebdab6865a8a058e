"""The failsafes live in the vehicle: kill the policy or the bridge in flight (real
processes, loopback Zenoh and UDP MAVLink) and the sim's commander still holds, lands
and disarms, as seen on the bus's ``status`` topic, on time in the vehicle's clock.

The graph is the one ``skyloop up`` starts (sim, perception, bridge, scripted policy),
started with the launcher's :class:`~skyloop.launcher.Graph` so the test can SIGKILL one
node. Short COM_OF_LOSS_T / SKY_HOLD_LAND_T and lockstep timeout keep it short.

Timing (issue 13: HOLD within COM_OF_LOSS_T, then LAND) is measured in the vehicle's
clock only, never from the test's kill (whose wall time lags the chain under load):
from the last setpoint the vehicle received (the last ``cmd_vel``, stamped with the
stack time of the step it answers) to the first HOLD status, and from it to LAND. A
status carries both clocks (``header.stamp``: stack time; ``vehicle_time``: the
commander's), which run together within an episode, so a status of the setpoint's
episode gives the setpoint's vehicle time (see :func:`assert_failsafe_timing`). The
status's own ``last_setpoint_time`` (the vehicle's record of the newest setpoint it took,
which tests/stack/test_stack_up.py times the failsafe by) must agree with that mapping.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import threading

import pytest
from loopback import free_port, wait_for

from bus import keys
from bus import messages as m
from bus.node import Bus
from bus.session import SessionConfig
from sitl.flight.vehicle import VehicleConfig
from skyloop.launcher import Graph

LOSS_S, HOLD_LAND_S = 0.5, 1.0  # COM_OF_LOSS_T, SKY_HOLD_LAND_T
PARAMS = ["--param", f"COM_OF_LOSS_T={LOSS_S}", "--param", f"SKY_HOLD_LAND_T={HOLD_LAND_S}"]
PERIOD_S = VehicleConfig().control_period  # the sim's control period (its default)
TOL_S = 1e-6  # float time


class StatusLog:
    """Every ``status`` of uav1: states in order (and the vehicle time and last setpoint
    time of each one's first status), event texts, every status's (stack time ns,
    vehicle time)."""

    def __init__(self, bus: Bus) -> None:
        self.lock = threading.Lock()
        self.states: list[str] = []
        self.entered: list[float] = []  # per state in ``states``
        self.last_setpoints: list[float] = []  # per state in ``states``
        self.clocks: list[tuple[int, float]] = []
        self.texts: list[str] = []
        self.failsafe_reasons: set[str] = set()
        self.crashed = False
        bus.subscribe(keys.STATUS, "uav1", self.on_status)

    def on_status(self, msg) -> None:
        with self.lock:
            stamp, vehicle_time = m.nanoseconds(msg.header.stamp), float(msg.vehicle_time)
            self.clocks.append((stamp, vehicle_time))
            if not self.states or self.states[-1] != msg.state:
                self.states.append(str(msg.state))
                self.entered.append(vehicle_time)
                self.last_setpoints.append(float(msg.last_setpoint_time))
            self.texts.extend(str(t) for t in msg.event_texts)
            if msg.failsafe:
                self.failsafe_reasons.add(str(msg.failsafe_reason))
            self.crashed = self.crashed or bool(msg.crashed)

    def since(self, n: int) -> list[str]:
        with self.lock:
            return list(self.states[n:])


class Steps:
    """The stack time (ns) of every step clock (-> episode, step) and of every
    ``cmd_vel`` (in order of arrival)."""

    def __init__(self, bus: Bus) -> None:
        self.lock = threading.Lock()
        self.clocks: dict[int, tuple[int, int]] = {}
        self.commands: list[int] = []
        bus.subscribe(keys.CMD_VEL, "uav1", self.on_command)

    def on_clock(self, msg) -> None:
        with self.lock:
            self.clocks[m.nanoseconds(msg.sim_time)] = (int(msg.episode), int(msg.step))

    def on_command(self, msg) -> None:
        with self.lock:
            self.commands.append(m.nanoseconds(msg.header.stamp))


@pytest.fixture
def flying():
    """The graph flying episodes in OFFBOARD (lockstep); yields (graph, status log,
    steps, killer)."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    env = dict(os.environ, SKYLOOP_ZENOH_MODE="peer", SKYLOOP_ZENOH_HUB=hub,
               PYTHONUNBUFFERED="1", MAVLINK20="1")
    env.pop("SKYLOOP_ZENOH_CONNECT", None)
    udp = [free_port(socket.SOCK_DGRAM) for _ in range(3)]
    graph = Graph(env)
    bus = Bus.open(SessionConfig(hub=hub))
    bus.watch_ready("*", graph.on_ready)  # the nodes' readiness tokens, as skyloop up
    status = StatusLog(bus)
    steps = Steps(bus)
    clocks: list[int] = []
    killer = EarlyKill()

    def on_clock(msg) -> None:
        clocks.append(int(msg.step))
        steps.on_clock(msg)
        killer.on_step(int(msg.step))

    bus.subscribe(keys.CLOCK, "uav1", on_clock)
    try:
        graph.start("perception", ["perception"])
        graph.start("bridge", ["bridge", "--api-port", str(udp[0]), "--api-local-port",
                               str(udp[1]), "--no-gcs", "--command-timeout", "2"])
        graph.start("policy", ["policy", "--policy", "scripted", "--api-port", str(udp[0])])
        sim = graph.start("sim", ["sim", "--episodes", "1000", "--max-steps", "100000",
                                  "--lockstep-timeout", "0.5", "--wait-go", *PARAMS],
                          stdin=subprocess.PIPE)
        for name in ("sim", "policy", "perception", "bridge"):  # every node's token
            assert graph.wait_for(graph.ready[name], name, 120.0) is None, name
        sim.proc.stdin.write("go\n")
        sim.proc.stdin.flush()
        wait_for(lambda: len(clocks) > 50, timeout=60.0, what="episodes flowing")
        assert status.since(0)[-1] == "OFFBOARD", status.states
        yield graph, status, steps, killer
    finally:
        graph.stop()
        bus.close()


class EarlyKill:
    """SIGKILLs a node as an episode's step ``KILL_STEP`` is published: early in the
    episode, so the vehicle holds well clear of what the scripted policy flies into
    (its episodes end in a collision after 25-40 steps; killed later, the vehicle can
    coast into the obstacle while holding, a crash rather than the failsafe under
    test)."""

    KILL_STEP = 2

    def __init__(self) -> None:
        self.pid: int | None = None
        self.done = threading.Event()

    def on_step(self, step: int) -> None:
        if self.pid is not None and step == self.KILL_STEP and not self.done.is_set():
            os.kill(self.pid, signal.SIGKILL)
            self.done.set()


def kill(graph: Graph, name: str, status: StatusLog, killer: EarlyKill) -> None:
    child = next(c for c in graph.children if c.name == name)
    killer.pid = child.proc.pid
    assert killer.done.wait(60.0), f"{name} not killed: no episode reached its step 2"
    with status.lock:  # from now on (the failsafe needs COM_OF_LOSS_T after the kill)
        status.texts, status.failsafe_reasons, status.crashed = [], set(), False
    child.proc.wait(5.0)


def assert_holds_lands_disarms(graph: Graph, status: StatusLog, steps: Steps) -> None:
    n = len(status.states)
    wait_for(lambda: "DISARMED" in status.since(n), timeout=60.0, what="disarmed")
    seq = status.since(n - 1)
    assert seq[:4] == ["OFFBOARD", "HOLD", "LAND", "DISARMED"], status.states
    assert "setpoint_loss" in status.failsafe_reasons
    for text in ("Failsafe: setpoints lost, holding", "Failsafe: landing",
                 "Landed, disarmed"):
        assert text in status.texts, status.texts
    assert not status.crashed
    sim = next(c for c in graph.children if c.name == "sim")
    assert sim.proc.poll() is None  # the vehicle is still running
    assert_failsafe_timing(status, steps, n)


def assert_failsafe_timing(status: StatusLog, steps: Steps, n: int) -> None:
    """HOLD at the first control step after no setpoint came for COM_OF_LOSS_T, LAND at
    the first one SKY_HOLD_LAND_T after HOLD (the commander's rule, PX4's), each to one
    control period, in the vehicle's clock; ``n``: the index of HOLD in ``status.states``.

    * HOLD: the first HOLD status's ``vehicle_time``, less one period (a status follows
      its step: the commander's clock has advanced past the step that switched).
    * The last setpoint: the last ``cmd_vel`` stamp S (stack time). It answers step k of
      episode e (its step clock); a status of that episode stamped after its start and
      at most S (the episode's first step's status is one: home moved) maps S to the
      vehicle time of step k, where the sim took it if it came in time for its step. It
      did iff the sim went on to step k + 1 of episode e (lockstep: a step whose command
      does not come within the timeout ends the episode). Otherwise (rare: a chain
      slower than the lockstep timeout, or a bridge killed between its sends to the test
      and to the sim) the vehicle took it later or never, so the vehicle's last setpoint
      is known only to be no older than step k - 1's (which let step k come): then only
      HOLD no sooner than COM_OF_LOSS_T after that one is asserted.
    * The HOLD status's ``last_setpoint_time`` (the vehicle's own record): S's vehicle
      time if it came in time, else no older than step k - 1's; and HOLD follows it as
      the rule says."""
    period_ns = round(PERIOD_S * 1e9)
    with steps.lock:
        last, clocks = steps.commands[-1], dict(steps.clocks)
    with status.lock:
        pairs, entered = list(status.clocks), list(status.entered)
        published = status.last_setpoints[n]
    assert last in clocks, ("the last setpoint answers no step seen", last, len(clocks))
    episode, step = clocks[last]
    start = last - step * period_ns
    same = [(stamp, t) for stamp, t in pairs if start < stamp <= last]
    assert same, ("no status of the setpoint's episode", episode, step, pairs[-20:])
    stamp, t = same[-1]
    setpoint = t - (stamp - last) / 1e9
    on_time = clocks.get(last + period_ns) == (episode, step + 1)
    assert clocks.get(last + 2 * period_ns) != (episode, step + 2), \
        "the vehicle answered a step by a command this test did not see"
    hold, land = entered[n] - PERIOD_S, entered[n + 1] - PERIOD_S
    what = (f"last setpoint at {setpoint:.2f} s (episode {episode} step {step}, "
            f"{'in time' if on_time else 'late'}; the vehicle says {published:.2f} s), "
            f"HOLD at {hold:.2f} s, LAND at {land:.2f} s")
    print(what)
    if on_time:
        assert LOSS_S + TOL_S < hold - setpoint <= LOSS_S + PERIOD_S + TOL_S, what
        assert abs(published - setpoint) <= TOL_S, what
    else:
        assert hold - (setpoint - PERIOD_S) > LOSS_S + TOL_S, what
        assert published >= setpoint - PERIOD_S - TOL_S, what
    assert LOSS_S + TOL_S < hold - published <= LOSS_S + PERIOD_S + TOL_S, what
    assert HOLD_LAND_S - TOL_S <= land - hold <= HOLD_LAND_S + PERIOD_S + TOL_S, what


def test_policy_killed_in_flight(flying) -> None:
    graph, status, steps, killer = flying
    kill(graph, "policy", status, killer)
    assert_holds_lands_disarms(graph, status, steps)


def test_bridge_killed_in_flight(flying) -> None:
    graph, status, steps, killer = flying
    kill(graph, "bridge", status, killer)
    assert_holds_lands_disarms(graph, status, steps)
