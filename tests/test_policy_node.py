"""The policy node's own checks, on a real bus and a real MAVLink socket (no vehicle)."""

from __future__ import annotations

import socket

import numpy as np
import pytest
from loopback import free_port

from bus import messages as m
from bus.session import Bus, SessionConfig
from mavlink_bridge.offboard_client import OffboardClientConfig
from policy.node import MAX_BAD_ACTIONS, PolicyNode


def test_an_actor_turning_nan_in_flight_is_refused_after_a_few_steps():
    bus = Bus.open(SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}"))
    outputs = iter([np.zeros(4)] + [np.full(4, np.nan)] * 10)
    node = PolicyNode(bus, lambda state: next(outputs), "uav1",
                      OffboardClientConfig(listen_port=free_port(socket.SOCK_DGRAM)))
    try:
        obs = np.zeros(35, np.float32)
        assert node.act(m.observation(obs, 0.0, episode=0, step=0)) is not None
        for step in range(1, MAX_BAD_ACTIONS):
            assert node.act(m.observation(obs, step * 0.1, episode=0, step=step)) is None
        assert node.bad_actions == MAX_BAD_ACTIONS - 1
        with pytest.raises(ValueError, match=r"non-finite .* \(episode 0 step 5"):
            node.act(m.observation(obs, 0.5, episode=0, step=MAX_BAD_ACTIONS))
    finally:
        node.close()
        bus.close()
