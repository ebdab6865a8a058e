"""The perception node under overload, over real loopback Zenoh: its queue is bounded
(drops counted, memory flat), and it stops cleanly with its bus."""

from __future__ import annotations

import numpy as np
import pytest
from loopback import free_port, wait_for

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
    assert node.dropped == 92


def test_queue_keeps_what_arrives_in_time(node_and_sender):
    node, sender = node_and_sender
    pub = sender.publisher(keys.PARAMS, "uav1")
    assert pub.wait_matched()
    pub.put(m.parameter("SKY_ICO_RADIUS", 3.5))
    wait_for(lambda: node.config.radius == 3.5, what="the parameter applied")
    assert node.dropped == 0
