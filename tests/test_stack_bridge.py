"""The bridge node over real loopback Zenoh and UDP MAVLink, in real time.

A policy node (scripted actor, its MAVLink client on a free port) arms, takes off and
enters OFFBOARD through the bridge; its setpoints come out on ``cmd_vel`` in the body
frame, stamped with the step they answer. Then the policy "dies" (its link closes) and
the bridge's commander falls to HOLD after 1.0 s of stack time, then LAND, and says so
on ``cmd_vel`` (world frame) without any help from the simulator.
"""

from __future__ import annotations

import socket
import threading

import numpy as np
import pytest
from loopback import free_port, wait_for

from bus import keys
from bus import messages as m
from bus.session import Bus, SessionConfig
from mavlink_bridge.node import BODY_FRAME, BridgeNode
from mavlink_bridge.offboard_client import OffboardClientConfig
from mavlink_bridge.vehicle_link import LinkConfig, VehicleLinkConfig
from policy.node import PolicyNode
from sitl.commander import Commander, VehicleSample


@pytest.fixture
def make_graph():
    opened: list = []

    def make(lockstep: bool):
        cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
        buses = [Bus.open(cfg) for _ in range(3)]
        api, local = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
        bridge = BridgeNode(buses[0], Commander(), VehicleSample, "uav1",
                            VehicleLinkConfig(api=LinkConfig(local, api), gcs=None),
                            lockstep=lockstep, lockstep_timeout_s=0.05)
        stop = threading.Event()
        thread = threading.Thread(target=bridge.run, args=(stop.is_set,), daemon=True)
        thread.start()
        policy = PolicyNode(buses[1], lambda s: np.array([1.0, 0.5, 0.25, 0.125], np.float32),
                            "uav1", OffboardClientConfig(listen_port=api), lockstep=lockstep)
        opened.append((stop, thread, policy, buses, bridge))
        return bridge, policy, buses[2]

    yield make
    for stop, thread, policy, buses, bridge in opened:
        stop.set()
        thread.join(5.0)
        policy.close()
        for bus in buses:
            bus.close()
        bridge.close()


def odom(k: int, z: float = 10.0):
    return m.odometry((0.0, 0.0, z), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), k / 10)


@pytest.mark.parametrize("lockstep", [False, True], ids=["realtime", "lockstep"])
def test_offboard_then_setpoint_loss_failsafe(make_graph, lockstep):
    """Lockstep: the bridge waits for each step's setpoint, and after lockstep_timeout_s
    of wall time flies on without it, so the failsafe acts as in real time."""
    bridge, policy, test_bus = make_graph(lockstep)
    pub_odom = test_bus.publisher(keys.ODOM, "uav1")
    pub_obs = test_bus.publisher(keys.OBSERVATION, "uav1")
    cmds = test_bus.inbox(keys.CMD_VEL, "uav1", maxsize=256)
    assert pub_odom.wait_matched() and pub_obs.wait_matched()
    policy.start(timeout=10.0)
    assert str(bridge.commander.state) == "OFFBOARD"

    for k in range(5):  # the policy answers each step; the bridge forwards, stamped
        pub_odom.put(odom(k))
        if not lockstep:  # real time forwards only answers to steps the bridge has seen
            wait_for(lambda k=k: bridge._last_stamp == k * 100_000_000, what=f"odom {k}")
        pub_obs.put(m.observation(np.zeros(35, np.float32), k / 10, 0, k))
        policy.spin_once(timeout=5.0)
        msg = cmds.get(timeout=5.0)
        assert msg.header.frame_id == BODY_FRAME
        assert m.nanoseconds(msg.header.stamp) == k * 100_000_000
        assert m.twist_values(msg) == (1.0, 0.5, 0.25, 0.125)

    policy.close()  # the policy process dies: no more setpoints
    for k in range(5, 80):  # 7.5 s of stack time
        pub_odom.put(odom(k))
        wait_for(lambda k=k: bridge._last_stamp == k * 100_000_000, what=f"odom {k}")
    wait_for(lambda: bridge.published >= (80 if lockstep else 5 + 60), what="commands")
    seen = []
    while (msg := cmds.get_nowait()) is not None:
        seen.append((m.nanoseconds(msg.header.stamp) // 100_000_000, msg.header.frame_id,
                     m.twist_values(msg)))
    if lockstep:  # the last setpoint is flown until the timeout, one command per step
        assert [k for k, _, _ in seen] == list(range(5, 80))
        assert all(f == BODY_FRAME for k, f, _ in seen if k < 14)
        assert bridge.missed >= 9
        seen = [x for x in seen if x[1] == "world"]
    assert all(frame == "world" for _, frame, _ in seen)
    first = seen[0][0]
    assert 14 <= first <= 16  # > 1.0 s after the last setpoint (step 4): HOLD
    assert seen[0][2] == (0.0, 0.0, 0.0, 0.0)
    assert seen[-1][2][2] < 0.0  # then LAND: descending
    assert str(bridge.commander.state) == "LAND"
