"""Readiness on the bus (issue 11): every node of ``skyloop up`` declares the liveliness
token ``skyloop/<vehicle>/ready/<node>`` once it can do its job, and the launcher waits
on those tokens, for every node it starts, never on a node's stdout.

* In-process: the perception node and the bridge hold their token from construction
  (subscribed, publishers declared, the bridge's MAVLink sockets bound) until ``close``.
* As programs: ``skyloop perception`` and ``skyloop bridge`` declare theirs.
* The launcher: :func:`skyloop.launcher.ready_waits` names every node it starts; a
  child that prints its ready line but holds no token is not ready (the wait times
  out), the token makes it ready, and its going clears it.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from loopback import free_port, started_blocked, wait_for

from bus.node import Bus
from bus.session import SessionConfig
from mavlink_bridge.node import BridgeNode
from mavlink_bridge.vehicle_link import LinkConfig, VehicleLinkConfig
from perception.node import PerceptionNode
from skyloop import launcher
from skyloop.cli.stack import parse_node
from skyloop.launcher import Child, Graph, nodes_of, ready_waits

ROOT = Path(__file__).resolve().parents[2]


class Seen:
    """The (node, alive) readiness events a watcher got, thread-safe."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.events: list[tuple[str, bool]] = []

    def __call__(self, node: str, alive: bool) -> None:
        with self.lock:
            self.events.append((node, alive))

    def has(self, event: tuple[str, bool]) -> bool:
        with self.lock:
            return event in self.events


@pytest.fixture
def hub():
    return SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")


def test_perception_and_bridge_hold_a_token_while_up(hub):
    watcher, node_bus = Bus.open(hub), Bus.open(hub)
    seen = Seen()
    perception = bridge = None
    try:
        watcher.watch_ready("uav1", seen)
        perception = PerceptionNode(node_bus, "uav1")
        udp = [free_port(socket.SOCK_DGRAM) for _ in range(2)]
        bridge = BridgeNode(node_bus, "uav1", VehicleLinkConfig(
            api=LinkConfig(udp[0], udp[1]), gcs=None))
        assert bridge.link.address("api")[1] == udp[0]  # bound before it said ready
        wait_for(lambda: seen.has(("perception", True)), what="perception's token")
        wait_for(lambda: seen.has(("bridge", True)), what="the bridge's token")
        assert perception.ready.key == "skyloop/uav1/ready/perception"
        assert bridge.ready.key == "skyloop/uav1/ready/bridge"
        perception.close()
        wait_for(lambda: seen.has(("perception", False)), what="perception's token gone")
        bridge.close()
        wait_for(lambda: seen.has(("bridge", False)), what="the bridge's token gone")
        perception = bridge = None
    finally:
        for n in (perception, bridge):
            if n is not None:
                n.close()
        node_bus.close()
        watcher.close()


def test_the_node_programs_declare_their_tokens(hub):
    """``skyloop perception`` and ``skyloop bridge`` (as ``skyloop up`` starts them)."""
    udp = [str(free_port(socket.SOCK_DGRAM)) for _ in range(2)]
    env = dict(os.environ, SKYLOOP_ZENOH_HUB=hub.hub, PYTHONUNBUFFERED="1")
    watcher = Bus.open(hub)
    seen = Seen()
    procs = []
    try:
        watcher.watch_ready("uav1", seen)
        for args in (["perception"], ["bridge", "--no-gcs", "--api-local-port", udp[0],
                                      "--api-port", udp[1]]):
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "skyloop", *args], cwd=ROOT, env=env,
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                start_new_session=True, preexec_fn=started_blocked))
        for name in ("perception", "bridge"):
            wait_for(lambda n=name: seen.has((n, True)), timeout=90.0,
                     what=f"{name}'s token")
        assert all(p.poll() is None for p in procs)
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        watcher.close()


@pytest.mark.parametrize("flags", [[], ["--log-dir", "LOG", "--viz", "save:x.rrd"],
                                   ["--policy", "none"], ["--router"]])
def test_the_launcher_waits_for_every_node_it_starts(flags):
    up = parse_node(["up", *flags]).resolved()
    waits = ready_waits(up)
    assert sorted(n for n, _ in waits) == sorted(nodes_of(up))
    assert {"perception", "bridge", "sim"} <= {n for n, _ in waits}
    assert all(t > 0 for _, t in waits)
    assert set(launcher.READY_NODES) == set(launcher.READY_TIMEOUT_S)


def test_a_ready_line_on_stdout_is_not_readiness(hub):
    """The launcher's graph sees a child print what its node prints once up (the sim's
    SKYLOOP-SIM-READY, perception's and the bridge's log lines) and still waits; the
    token makes it ready; the token gone, it is not ready any more."""
    env = dict(os.environ, SKYLOOP_ZENOH_HUB=hub.hub)
    graph = Graph(env)
    lines = [launcher.SIM_READY_LINE, "perception up for uav1", "bridge up: api"]
    proc = subprocess.Popen(
        [sys.executable, "-c", f"import time\nfor l in {lines!r}: print(l, flush=True)\n"
                               "time.sleep(60)"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    child = Child("sim", proc)
    graph.children.append(child)
    child.reader = threading.Thread(target=graph._read, args=(child,), daemon=True)
    child.reader.start()
    watcher, node = Bus.open(hub), Bus.open(hub)
    try:
        watcher.watch_ready("uav1", graph.on_ready)
        wait_for(lambda: len(child.lines) == len(lines), what="the child's lines read")
        for name in ("sim", "perception", "bridge"):
            with pytest.raises(TimeoutError, match=f"{name} not ready"):
                graph.wait_for(graph.ready[name], name, 0.3)
        tokens = {name: node.declare_ready("uav1", name) for name in ("sim", "perception",
                                                                       "bridge")}
        node.declare_ready("uav2", "policy")  # another vehicle's: not this stack's
        for name in tokens:
            assert graph.wait_for(graph.ready[name], name, 10.0) is None
        tokens["perception"].close()
        wait_for(lambda: not graph.ready["perception"].is_set(), what="perception gone")
        assert graph.ready["sim"].is_set() and not graph.ready["policy"].is_set()
    finally:
        node.close()
        watcher.close()
        proc.kill()
        proc.wait()
