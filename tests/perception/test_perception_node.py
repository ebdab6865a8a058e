"""The perception node under overload, over real loopback Zenoh: its queue is bounded
(drops counted, memory flat), episode events and parameters included, and it stops
cleanly with its bus, in-process and as ``skyloop perception`` flooded, then SIGTERMed."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from loopback import free_port, session_members, started_blocked, wait_for

from bus import keys
from bus import messages as m
from bus.node import Bus
from bus.session import SessionConfig
from perception.node import PerceptionNode


@pytest.fixture
def node_and_sender():
    """A perception node with a queue of 8 on one bus, a second bus to publish from."""
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    node_bus, sender = Bus.open(cfg), Bus.open(cfg)
    node = PerceptionNode(node_bus, "uav1", queue_size=8)
    yield node, sender
    node.close()
    sender.close()
    node_bus.close()  # after the node: no publish on a closed publisher


def test_overload_is_dropped_and_counted_not_queued(node_and_sender):
    node, sender = node_and_sender
    pub = sender.publisher(keys.LIDAR_POINTS, "uav1")
    assert pub.wait_matched()
    events = sender.publisher(keys.EPISODE, "uav1")
    assert events.wait_matched()
    node._stop.set()  # the worker stops draining (as close() does, minus the join)
    node._thread.join(5.0)
    node._stop.clear()  # ... but the node still takes messages
    scan = m.pointcloud(np.ones((1000, 3), np.float32), 0.0)
    for _ in range(100):
        pub.put(scan)
    wait_for(lambda: node.dropped == 92, what="the overflow counted")
    assert node._q.qsize() == 8  # bounded
    events.put(m.episode_start(0, 1, (0, 0, 1), (9, 0, 1), 0.0))  # a full queue takes it
    wait_for(lambda: node._q.qsize() == 9, what="the START queued all the same")
    assert node.dropped == 92 and node.dropped_events == 0
    # ... but a flood of events is bounded too: 8 more places, then dropped and counted
    for i in range(1, 11):
        events.put(m.episode_start(i, 1, (0, 0, 1), (9, 0, 1), 0.0))
    wait_for(lambda: node.dropped_events == 3, what="the events' overflow counted")
    assert node._q.qsize() == 16 and node.dropped == 95


def test_queue_keeps_what_arrives_in_time(node_and_sender):
    node, sender = node_and_sender
    pub = sender.publisher(keys.PARAMS, "uav1")
    assert pub.wait_matched()
    pub.put(m.parameter("SKY_ICO_RADIUS", 3.5))
    wait_for(lambda: node.config.radius == 3.5, what="the parameter applied")
    assert node.dropped == 0


@pytest.mark.timing
def test_flooded_then_sigterm_exits_fast_and_clean(tmp_path):
    """``skyloop perception`` flooded with whole steps (clock, odometry, a 2,000-point
    scan; an episode START first) as fast as this process can publish them, then
    SIGTERMed in the flood: it exits within 2 s, 0, with no traceback and no "publisher
    ... is closed" (the worker publishing on a closed bus: 2,530 such lines, seen), and
    its last line counts what it published and dropped (both > 0: it was overloaded)."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen(
        [sys.executable, "-m", "skyloop", "perception"], cwd=Path(__file__).resolve().parents[2],
        env=dict(os.environ, SKYLOOP_ZENOH_HUB=hub, PYTHONUNBUFFERED="1"),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True, preexec_fn=started_blocked)
    lines: list[str] = []
    up = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            if "perception up" in line:
                up.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    sender = Bus.open(SessionConfig(hub=hub))
    stop = threading.Event()
    sent = [0]

    def flood(pubs: dict) -> None:
        rng = np.random.default_rng(0)
        scan = rng.uniform(-4, 4, (2000, 3)).astype(np.float32)
        steps = []  # encoded once: publishing, not encoding, sets the pace
        for i in range(200):
            t = 0.1 * i
            steps.append([(pubs[keys.CLOCK], m.encode(m.step_clock(i, t, 0))),
                          (pubs[keys.ODOM], m.encode(m.odometry((0, 0, 1), (0, 0, 0),
                                                                (0, 0, 0, 1), t))),
                          (pubs[keys.LIDAR_POINTS], m.encode(m.pointcloud(scan, t)))])
        while not stop.is_set():
            for step in steps:
                for pub, data in step:
                    pub.put_bytes(data)
                sent[0] += 1

    try:
        assert up.wait(60), "".join(lines)
        pubs = {t: sender.publisher(t, "uav1") for t in (keys.EPISODE, keys.CLOCK, keys.ODOM,
                                                         keys.LIDAR_POINTS)}
        assert all(p.wait_matched() for p in pubs.values())
        pubs[keys.EPISODE].put(m.episode_start(0, 1, (0, 0, 1), (9, 0, 1), 0.0))
        flooder = threading.Thread(target=flood, args=(pubs,), daemon=True)
        flooder.start()
        wait_for(lambda: any("overloaded" in x for x in lines), timeout=30,
                 what="perception overloaded")
        time.sleep(0.5)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=15)
        took = time.monotonic() - t0
    finally:
        stop.set()
        if proc.poll() is None:
            proc.kill()
    flooder.join(5)
    sender.close()
    reader.join(5)
    out = "".join(lines)
    assert took < 2.0, (took, out[-3000:])
    assert proc.returncode == 0, out[-3000:]
    assert "is closed" not in out and "Traceback" not in out, out[-3000:]
    assert session_members(proc.pid) == []
    counts = re.search(r"published (\d+) observations, dropped (\d+) messages", out)
    assert counts is not None, out[-3000:]
    assert int(counts[1]) > 0 and int(counts[2]) > 0, (counts[0], sent[0])
