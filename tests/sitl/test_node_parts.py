"""The simulator node's parts on their own, without a bus: the config it resolves, the
command gate (lockstep timeout, then one period per step until a command matches; stale
and late commands), and the rejoin state after a broken episode."""

from __future__ import annotations

import queue
import time

import pytest

from bus import messages as m
from sitl.commander.machine import State
from sitl.episode import EpisodeConfig
from sitl.node.pacing import CommandGate, Pacer, Rejoin, StackClock
from sitl.node.step import SimNodeConfig

PERIOD_NS = 100_000_000


class Inbox:
    """``bus.node`` inbox: ``get(timeout)`` raises TimeoutError, ``get_nowait`` None."""

    def __init__(self) -> None:
        self.q: queue.Queue = queue.Queue()

    def put(self, msg) -> None:
        self.q.put(msg)

    def get(self, timeout: float):
        try:
            return self.q.get(timeout=timeout)
        except queue.Empty:
            raise TimeoutError from None

    def get_nowait(self):
        try:
            return self.q.get_nowait()
        except queue.Empty:
            return None


class Cmdr:
    def __init__(self) -> None:
        self.state = State.OFFBOARD
        self.offboard_asked = float("-inf")
        self.offered: list[tuple] = []

    def setpoint(self, now, vx, vy, vz, yaw_rate, body, yaw=None) -> None:
        self.offered.append((now, vx, body))


def cmd(step: int, vx: float = 1.0):
    return m.velocity_setpoint((vx, 0.0, 0.0), 0.0, step * PERIOD_NS / 1e9, body=True)


def gate(timeout_s: float = 0.3):
    clock, rejoin, cmdr, inbox = StackClock(PERIOD_NS), Rejoin(), Cmdr(), Inbox()
    served: list[int] = []
    g = CommandGate(inbox, cmdr, clock, rejoin, timeout_s, serve=lambda: served.append(1))
    return g, clock, rejoin, cmdr, inbox, served


def test_resolved_config_leaves_the_given_one_alone() -> None:
    given = SimNodeConfig(goals_from_bus=True, scenario="forest", episode=EpisodeConfig())
    before = repr(given)
    r = given.resolved()
    assert r.free_flight and r.realtime and r.episode.scenario == "forest"
    assert repr(given) == before and r is not given and r.episode is not given.episode
    plain = SimNodeConfig().resolved()
    assert not plain.free_flight and not plain.realtime


def test_lockstep_gate_matches_counts_and_shortens_waits_after_a_miss() -> None:
    g, clock, rejoin, cmdr, inbox, served = gate(timeout_s=1.5)
    clock.g = 5
    inbox.put(cmd(4))  # an old one: stale, offered to the commander all the same
    inbox.put(cmd(5))
    assert m.nanoseconds(g.wait(time.monotonic(), None).header.stamp) == 5 * PERIOD_NS
    assert (g.stale, g.missed, len(g.latencies_ms), len(cmdr.offered)) == (1, 0, 1, 2)
    clock.g = 6
    t = time.monotonic()
    assert g.wait(t, None) is None  # nothing came: the full timeout
    assert time.monotonic() - t >= 1.5 and g.missed == 1 and rejoin.missing and served
    t = time.monotonic()
    assert g.wait(t, None) is None  # still missing: one period only
    assert time.monotonic() - t < 1.0 and g.missed == 2
    inbox.put(cmd(6))
    assert g.wait(time.monotonic(), None) is not None and not rejoin.missing
    rejoin.missing = True
    rejoin.episode_started()  # each episode waits the full timeout for its first command
    assert rejoin.lockstep_wait(2.0, 0.1) == 2.0


def test_lockstep_wait_ends_when_a_request_leaves_offboard() -> None:
    g, _, _, cmdr, _, served = gate(timeout_s=5.0)
    cmdr.state = State.HOLD
    t = time.monotonic()
    assert g.wait(t, None) is None and time.monotonic() - t < 1.0
    assert served and g.missed == 0


def test_realtime_gate_flies_the_newest_older_command_at_the_deadline() -> None:
    g, clock, _, _, inbox, _ = gate()
    clock.g = 3
    inbox.put(cmd(2, vx=0.5))
    inbox.put(cmd(9, vx=0.9))  # from the future: never flown
    got = g.wait(time.monotonic(), time.monotonic() + 0.05)
    assert m.setpoint_values(got)[0] == 0.5 and g.late == 1 and g.stale == 2


def test_take_and_drain_offer_everything_queued() -> None:
    g, _, _, cmdr, inbox, _ = gate()
    assert not g.take(0.01)
    for k in range(3):
        inbox.put(cmd(k))
    assert g.take(0.01) and len(cmdr.offered) == 3
    assert m.nanoseconds(g.last.header.stamp) == 2 * PERIOD_NS
    inbox.put(cmd(7))
    g.drain()
    assert len(cmdr.offered) == 4 and m.nanoseconds(g.last.header.stamp) == 7 * PERIOD_NS


def test_rejoin_after_a_broken_episode() -> None:
    rejoin, cmdr = Rejoin(), Cmdr()
    assert not rejoin.pending
    rejoin.broke(10.0, late_stamp=42 * PERIOD_NS)
    assert rejoin.pending
    assert not rejoin.rejoined(cmdr, None)  # in OFFBOARD, but asked before the break
    assert not rejoin.rejoined(cmdr, cmd(41))
    assert rejoin.rejoined(cmdr, cmd(42))  # the missed step's late answer: a slow policy
    cmdr.state = State.HOLD
    assert not rejoin.rejoined(cmdr, cmd(42))  # only while still in OFFBOARD
    cmdr.state, cmdr.offboard_asked = State.OFFBOARD, 10.5  # a restarted policy asked
    assert rejoin.rejoined(cmdr, None)
    rejoin.clear()
    assert not rejoin.pending and rejoin.late_stamp is None
    rejoin.broke(20.0, late_stamp=None)  # it left OFFBOARD: only a new ask will do
    assert not rejoin.rejoined(cmdr, cmd(42))


@pytest.mark.timing
def test_pacer_ticks_at_the_period_and_serves_meanwhile() -> None:
    served: list[int] = []
    pacer = Pacer(0.05, lambda: served.append(1))
    t0 = time.monotonic()
    for _ in range(4):
        pacer.pace()
    assert 0.13 <= time.monotonic() - t0 < 1.0 and len(served) >= 4
    slow = Pacer(3.0, lambda: None)
    slow.pace()
    slow.release()
    t = time.monotonic()
    slow.pace()  # released: the next paced step starts at once, not a period later
    assert time.monotonic() - t < 1.5
