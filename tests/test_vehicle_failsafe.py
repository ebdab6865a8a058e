"""The failsafes live in the vehicle: kill the policy or the bridge in flight (real
processes, loopback Zenoh and UDP MAVLink) and the sim's commander still holds, lands
and disarms, as seen on the bus's ``status`` topic.

The graph is the one ``skyloop up`` starts (sim, perception, bridge, scripted policy),
started with the launcher's :class:`~skyloop.launcher.Graph` so the test can SIGKILL one
node. Short COM_OF_LOSS_T / SKY_HOLD_LAND_T and lockstep timeout keep it short.
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
from bus.node import Bus
from bus.session import SessionConfig
from skyloop.launcher import Graph

PARAMS = ["--param", "COM_OF_LOSS_T=0.5", "--param", "SKY_HOLD_LAND_T=1.0"]


class StatusLog:
    """Every ``status`` of uav1: states in order and event texts."""

    def __init__(self, bus: Bus) -> None:
        self.lock = threading.Lock()
        self.states: list[str] = []
        self.texts: list[str] = []
        self.failsafe_reasons: set[str] = set()
        self.crashed = False
        bus.subscribe(keys.STATUS, "uav1", self.on_status)

    def on_status(self, msg) -> None:
        with self.lock:
            if not self.states or self.states[-1] != msg.state:
                self.states.append(str(msg.state))
            self.texts.extend(str(t) for t in msg.event_texts)
            if msg.failsafe:
                self.failsafe_reasons.add(str(msg.failsafe_reason))
            self.crashed = self.crashed or bool(msg.crashed)

    def since(self, n: int) -> list[str]:
        with self.lock:
            return list(self.states[n:])


@pytest.fixture
def flying():
    """The graph flying episodes in OFFBOARD (lockstep); yields (graph, status log, killer)."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    env = dict(os.environ, SKYLOOP_ZENOH_MODE="peer", SKYLOOP_ZENOH_HUB=hub,
               PYTHONUNBUFFERED="1", MAVLINK20="1")
    env.pop("SKYLOOP_ZENOH_CONNECT", None)
    udp = [free_port(socket.SOCK_DGRAM) for _ in range(3)]
    graph = Graph(env)
    bus = Bus.open(SessionConfig(hub=hub))
    bus.watch_ready("*", graph.on_ready)  # the nodes' readiness tokens, as skyloop up
    status = StatusLog(bus)
    clocks: list[int] = []
    killer = EarlyKill()

    def on_clock(msg) -> None:
        clocks.append(int(msg.step))
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
        for name in ("sim", "policy"):
            assert graph.wait_for(graph.ready[name], name, 120.0) is None, name
        sim.proc.stdin.write("go\n")
        sim.proc.stdin.flush()
        wait_for(lambda: len(clocks) > 50, timeout=60.0, what="episodes flowing")
        assert status.since(0)[-1] == "OFFBOARD", status.states
        yield graph, status, killer
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


def assert_holds_lands_disarms(graph: Graph, status: StatusLog) -> None:
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


def test_policy_killed_in_flight(flying) -> None:
    graph, status, killer = flying
    kill(graph, "policy", status, killer)
    assert_holds_lands_disarms(graph, status)


def test_bridge_killed_in_flight(flying) -> None:
    graph, status, killer = flying
    kill(graph, "bridge", status, killer)
    assert_holds_lands_disarms(graph, status)
