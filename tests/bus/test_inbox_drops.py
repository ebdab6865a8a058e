"""The sim's and the policy's bounded inboxes under overload (issue 13): a full inbox
drops its oldest message and counts it, and the node's counters (its last line for
``skyloop up``, ``SKYLOOP-COUNTERS``) report the drops per inbox and in total. Real
loopback Zenoh, nothing consuming the inboxes (the nodes are built, never run)."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from loopback import free_port, wait_for

from bus import keys
from bus import messages as m
from bus.node import Bus
from bus.session import SessionConfig


@pytest.fixture
def buses():
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    node_bus, bus = Bus.open(cfg), Bus.open(cfg)
    yield node_bus, bus
    bus.close()
    node_bus.close()


def _flood(bus: Bus, topic: str, msgs: list, inbox) -> None:
    pub = bus.publisher(topic, "uav1")
    assert pub.wait_matched()
    for msg in msgs:
        pub.put(msg)
    wait_for(lambda: inbox.subscription.received == len(msgs), what=f"{topic} received")


def test_policy_counts_what_its_full_inboxes_drop(buses) -> None:
    from mavlink_bridge.offboard_client import OffboardClientConfig
    from policy.nodes.node import PolicyNode

    node_bus, bus = buses
    node = PolicyNode(node_bus, lambda state: np.zeros(4), "uav1",
                      OffboardClientConfig(listen_port=free_port(socket.SOCK_DGRAM)))
    try:
        assert node.counters() == {"sent": 0, "refusals": 0, "bad_actions": 0,
                                   "dropped": 0, "dropped_observation": 0,
                                   "dropped_params": 0}
        obs = np.zeros(35, np.float32)
        _flood(bus, keys.OBSERVATION, [m.observation(obs, i * 0.1, episode=0, step=i)
                                       for i in range(100)], node.inbox)  # holds 64
        _flood(bus, keys.PARAMS, [m.parameter("COM_OF_LOSS_T", 1.0 + i)
                                  for i in range(70)], node.params)  # holds 64
        c = node.counters()
        assert (c["dropped_observation"], c["dropped_params"], c["dropped"]) == (36, 6, 42)
        assert len(node.inbox) == 64
        # the oldest went: the first observation left is step 36
        assert node.inbox.get_nowait().step == 36
    finally:
        node.close()


def test_sim_counts_what_its_full_inboxes_drop(buses) -> None:
    from sitl.node.node import SimNode, SimNodeConfig

    node_bus, bus = buses
    node = SimNode(node_bus, SimNodeConfig(realtime=True, match_timeout_s=0.1))
    assert node.counters() == {"dropped": 0, "dropped_cmd_vel": 0, "dropped_goal": 0,
                               "dropped_params": 0}
    _flood(bus, keys.CMD_VEL, [m.velocity_setpoint((0.1, 0.0, 0.0), 0.0, i * 0.1, body=True)
                               for i in range(300)], node.cmds)  # holds 256
    _flood(bus, keys.GOAL, [m.pose_stamped((1.0, 2.0, 3.0), 0.0) for _ in range(20)],
           node.goals.inbox)  # holds 16
    assert node.counters() == {"dropped": 48, "dropped_cmd_vel": 44, "dropped_goal": 4,
                               "dropped_params": 0}
