"""The bridge node as the vehicle's MAVLink face, over real loopback Zenoh and UDP.

The vehicle side is the sim's real :class:`~sitl.node.vehicle_service.VehicleService` (the
commander's requests, status and events on the bus) without the flight model: the test
serves it, and offers it the ``cmd_vel`` setpoints, between the offboard client's polls.
Checked: no heartbeat until the vehicle reported a status; arm/takeoff/offboard reach
the sim's commander and come back as COMMAND_ACK with the heartbeat following; events
become STATUSTEXT; setpoints are forwarded on ``cmd_vel`` with their frame and
``time_boot_ms`` stamp, exact re-sends once; a vehicle that does not answer gives
TEMPORARILY_REJECTED, counted.
"""

from __future__ import annotations

import socket
import threading
import time

import pytest
from loopback import free_port, wait_for

from bus import keys
from bus import messages as m
from bus.node import Bus
from bus.session import SessionConfig
from mavlink_bridge.modes import OFFBOARD
from mavlink_bridge.node import BridgeNode
from mavlink_bridge.offboard_client import (
    CommandRejected,
    OffboardClient,
    OffboardClientConfig,
    OffboardError,
)
from mavlink_bridge.transport import mavlink
from mavlink_bridge.vehicle_link import LinkConfig, VehicleLinkConfig
from sitl.commander.machine import Commander, State, VehicleSample
from sitl.node.vehicle_service import VehicleService


class Graph:
    """A bridge (own thread), the sim's vehicle service and an offboard client."""

    def __init__(self, command_timeout_s: float = 1.0) -> None:
        cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
        self.buses = [Bus.open(cfg) for _ in range(3)]
        api, local = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
        self.bridge = BridgeNode(self.buses[0], "uav1",
                                 VehicleLinkConfig(api=LinkConfig(local, api), gcs=None),
                                 command_timeout_s=command_timeout_s)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.bridge.run, args=(self.stop.is_set,),
                                       daemon=True)
        self.thread.start()
        self.commander = Commander()
        self.service: VehicleService | None = None
        self.t = 0.0
        self.client = OffboardClient(OffboardClientConfig(listen_port=api, command_timeout=0.3),
                                     spin=self.spin)
        self.test_bus = self.buses[2]

    def start_vehicle(self) -> None:
        self.service = VehicleService(self.buses[1], "uav1", self.commander, None)
        self.cmds = self.buses[1].inbox(keys.CMD_VEL, "uav1", maxsize=256)
        self.service.publish_status(0.0, 0.0, force=True)

    def spin(self) -> None:
        """What the sim does between two client polls: serve requests, one step."""
        if self.service is not None:
            while (msg := self.cmds.get_nowait()) is not None:  # as the sim offers them
                self.commander.setpoint(self.t, *m.setpoint_values(msg),
                                        body=msg.frame == m.FRAME_BODY)
            self.service.serve(self.t)
            self.commander.step(self.t, VehicleSample(0.0, 0.0, 0.0, 0.0))
            self.service.publish_status(0.0, self.t)
            self.t += 0.01
        time.sleep(0.002)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5.0)
        self.client.close()
        for bus in self.buses:
            bus.close()
        self.bridge.close()


@pytest.fixture
def graph():
    made: list[Graph] = []

    def make(**kwargs) -> Graph:
        made.append(Graph(**kwargs))
        return made[-1]

    yield make
    for g in made:
        g.close()


def test_commands_reach_the_sims_commander(graph) -> None:
    g = graph()
    with pytest.raises(OffboardError):  # no status from a vehicle yet: no heartbeat
        g.client.wait_heartbeat(0.5)
    g.start_vehicle()
    g.client.wait_heartbeat(5.0)
    assert not g.client.armed
    g.client.arm()
    assert g.commander.state == State.ARMED
    assert g.client.wait(lambda: g.client.armed, 2.0)  # the heartbeat follows the answer
    with pytest.raises(CommandRejected) as err:  # refused by the sim's commander: DENIED
        g.client.takeoff(700.0)  # AMSL (above home's 488 m): 212 m up, more than 100 m
    assert err.value.result == mavlink.MAV_RESULT_DENIED
    g.client.takeoff(2.0)
    assert g.commander.state == State.TAKEOFF
    g.client.set_velocity_body(0.0, 0.0, 0.0, 0.0)
    g.client.start_offboard()  # stream, switch, heartbeat shows OFFBOARD
    assert g.commander.state == State.OFFBOARD and g.client.mode == OFFBOARD
    texts = [t for _, t in g.client.statustexts]  # every event, refusals included
    assert texts[:2] == ["Armed", "Takeoff denied: bad altitude"]
    assert "Takeoff to 2.0 m" in texts and "Offboard" in texts
    assert g.bridge.commander.timeouts == 0


def test_setpoints_forwarded_with_frame_and_stamp(graph) -> None:
    g = graph()
    cmds = g.test_bus.inbox(keys.CMD_VEL, "uav1", maxsize=64)
    g.start_vehicle()
    g.client.wait_heartbeat(5.0)
    g.client.config.setpoint_period = 1e9  # no timer re-sends: one message per call
    g.client.set_velocity_body(1.0, 0.5, 0.25, 0.125, time_boot_ms=1234)
    g.client.resend()  # an exact re-send: not forwarded again
    g.client.set_velocity_enu(-1.0, 2.0, 0.0, 0.5, time_boot_ms=1300)
    msgs = [cmds.get(timeout=5.0), cmds.get(timeout=5.0)]
    assert msgs[0].frame == m.FRAME_BODY and not msgs[0].heading
    assert msgs[0].header.frame_id == "base_link"  # for ROS tools; ``frame`` is the contract
    assert m.nanoseconds(msgs[0].header.stamp) == 1_234_000_000
    assert m.setpoint_values(msgs[0]) == (1.0, 0.5, 0.25, 0.125)
    assert msgs[1].frame == m.FRAME_WORLD and msgs[1].header.frame_id == "world"
    assert m.nanoseconds(msgs[1].header.stamp) == 1_300_000_000
    assert m.setpoint_values(msgs[1]) == (-1.0, 2.0, 0.0, 0.5)
    wait_for(lambda: g.bridge.resends == 1 and g.bridge.published == 2, what="counters")
    assert cmds.get_nowait() is None
    g.client.set_velocity_enu(-1.0, 2.0, 0.0, 0.5, time_boot_ms=0)  # 0: not stamped
    g.client.resend()  # each unstamped one is forwarded (MAVProxy's stream)
    assert [m.nanoseconds(cmds.get(timeout=5.0).header.stamp) for _ in range(2)] == [0, 0]
    # (the bridge counts after the put: the messages may arrive first)
    wait_for(lambda: g.bridge.resends == 1 and g.bridge.published == 4, what="counters")


def test_a_vehicle_that_does_not_answer_is_busy(graph) -> None:
    g = graph(command_timeout_s=0.2)
    silent = g.buses[1].queryable(keys.COMMAND, "uav1")  # declared, never answered
    status = g.buses[1].publisher(keys.STATUS, "uav1")
    assert status.wait_matched()
    status.put(m.vehicle_status(0.0, 0.0, 0, "DISARMED", False, True, None, False))
    g.client.spin = lambda: time.sleep(0.002)
    g.client.wait_heartbeat(5.0)
    result = g.client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    assert result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    assert g.bridge.commander.timeouts >= 1 and len(silent.take()) >= 1  # it was asked


def test_proxy_keeps_the_newest_state_and_follows_a_restarted_sim() -> None:
    from mavlink_bridge.node import CommanderProxy

    proxy = CommanderProxy(None, "uav1")  # update() needs no bus
    assert proxy.update(m.vehicle_status(0.0, 5.0, 3, "HOLD", True, False, None, False))
    assert proxy.update(m.command_ack(True, "", "LAND", True, False, False, 4))
    assert not proxy.update(m.vehicle_status(0.0, 5.1, 3, "HOLD", True, False, None, False))
    assert proxy.state == "LAND"  # the older status lost to the newer answer
    assert proxy.update(m.vehicle_status(0.0, 0.0, 0, "DISARMED", False, True, None, False))
    assert (proxy.state, proxy.armed, proxy.landed) == ("DISARMED", False, True)  # restarted


def test_a_status_flood_is_bounded_dropped_oldest_first_and_counted() -> None:
    """The sim's status and episode messages wait for the bridge's loop in a bounded
    queue: with the loop not running, 40 statuses into a queue of 16 leave 16 queued and
    24 dropped (counted); the loop then takes the newest state."""
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    node_bus, sender = Bus.open(cfg), Bus.open(cfg)
    api, local = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    bridge = BridgeNode(node_bus, "uav1", VehicleLinkConfig(api=LinkConfig(local, api), gcs=None),
                        queue_size=16)
    try:
        pub = sender.publisher(keys.STATUS, "uav1")
        assert pub.wait_matched()
        for revision in range(40):
            pub.put(m.vehicle_status(0.0, 0.1 * revision, revision, "HOLD", True, False, None,
                                     False))
        wait_for(lambda: bridge.dropped == 24, what="the overflow counted")
        assert bridge._q.qsize() == 16
        bridge.spin_once(0.0)
        assert bridge._q.qsize() == 0 and bridge.commander.revision == 39
        assert bridge.counters()["dropped"] == 24
    finally:
        sender.close()
        node_bus.close()
        bridge.close()
