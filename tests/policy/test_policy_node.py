"""The policy node's own checks, on a real bus and a real MAVLink socket (no vehicle)."""

from __future__ import annotations

import os
import socket
import threading
import time

import numpy as np
import pytest
from loopback import free_port, wait_for

os.environ["MAVLINK20"] = "1"  # before mavutil is imported
from pymavlink import mavutil  # noqa: E402

from bus import messages as m  # noqa: E402
from bus.node import Bus  # noqa: E402
from bus.session import SessionConfig  # noqa: E402
from bus.task import TASK  # noqa: E402
from mavlink_bridge.node import BridgeNode  # noqa: E402
from mavlink_bridge.offboard_client import OffboardClientConfig  # noqa: E402
from mavlink_bridge.transport import mavlink  # noqa: E402
from mavlink_bridge.vehicle_link import LinkConfig, VehicleLinkConfig  # noqa: E402
from perception.observation import ObservationConfig, scaling_fields  # noqa: E402
from policy.nodes.node import MAX_BAD_ACTIONS, PolicyNode  # noqa: E402
from sitl.commander.machine import Commander  # noqa: E402
from sitl.node.vehicle_service import VehicleService  # noqa: E402


def stop_all(stop: threading.Event, threads, closers, buses) -> None:
    """A test's teardown: stop the loops, join their threads, close the nodes, then the
    buses."""
    stop.set()
    for thread in threads:
        thread.join(5.0)
    for each in closers:
        each.close()
    for bus in buses:
        bus.close()

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


def test_no_flight_under_parameters_the_actor_was_not_trained_for(tmp_path):
    """A ground station sets MPC_XY_VEL_MAX under a policy trained with 2 m/s: the policy
    node stops answering steps, asks HOLD and says why in a STATUSTEXT that reaches the
    ground station; set back, it flies again. An observation made with another
    icosahedron radius stops it too. Real parts: the bridge (own thread), the sim's
    vehicle service and commander, the policy node's MAVLink client, a pymavlink GCS."""
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    buses = [Bus.open(cfg) for _ in range(3)]
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255,
                                     source_component=190, dialect="common")
    api, api_local = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    bridge = BridgeNode(buses[0], "uav1", VehicleLinkConfig(
        api=LinkConfig(api_local, api),
        gcs=LinkConfig(free_port(socket.SOCK_DGRAM), gcs.port.getsockname()[1]),
        params_file=str(tmp_path / "params.json")))
    stop = threading.Event()
    thread = threading.Thread(target=bridge.run, args=(stop.is_set,), daemon=True)
    commander = Commander()
    commander.place(0.0, True, "OFFBOARD")  # flying an episode
    service = VehicleService(buses[1], "uav1", commander, None)
    node = PolicyNode(buses[2], lambda state: np.full(4, 0.5), "uav1",
                      OffboardClientConfig(listen_port=api), trained=TASK)
    def vehicle() -> None:  # the sim's control steps
        t = 0.0
        while not stop.is_set():
            service.serve(t)
            service.publish_status(0.0, t, force=True)
            t += 0.1
            time.sleep(0.01)

    sim = threading.Thread(target=vehicle, daemon=True)
    thread.start()
    sim.start()
    texts: list[str] = []

    def spin() -> None:  # the node's step and the GCS's
        node.spin_once(0.01)
        while (msg := gcs.recv_match(type="STATUSTEXT", blocking=False)) is not None:
            texts.append(msg.text)

    def said(what: str) -> bool:
        spin()
        return any(what in x for x in texts)

    try:
        wait_for(lambda: (spin(), node.client.vehicle is not None)[1], 10.0, "the vehicle")
        wait_for(lambda: gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=0.1)
                 is not None or (spin() and False), 10.0, "the GCS link")
        obs = np.zeros(35, np.float32)
        scaling = scaling_fields(ObservationConfig())
        assert node.act(m.observation(obs, 0.0, 0, 0, scaling=scaling)) is not None

        gcs.mav.param_set_send(1, 1, b"MPC_XY_VEL_MAX", 1.0, mavlink.MAV_PARAM_TYPE_REAL32)
        wait_for(lambda: said("MPC_XY_VEL_MAX=1 m/s, trained with 2"), 10.0,
                 "the policy's refusal at the ground station")
        assert node.refusals == 1 and set(node.off_task) == {"MPC_XY_VEL_MAX"}
        sent = node.sent
        assert node.act(m.observation(obs, 0.1, 0, 1, scaling=scaling)) is None
        assert node.sent == sent  # nothing flown
        hold = f"cmd.{mavlink.MAV_CMD_DO_SET_MODE}.{mavlink.MAV_RESULT_ACCEPTED}"
        assert bridge.link.counters[hold] == 1, bridge.link.counters
        assert commander.state == "HOLD"

        gcs.mav.param_set_send(1, 1, b"MPC_XY_VEL_MAX", 2.0, mavlink.MAV_PARAM_TYPE_REAL32)
        wait_for(lambda: said("parameters as trained"), 10.0, "flying again")
        assert node.act(m.observation(obs, 0.2, 0, 2, scaling=scaling)) is not None
        assert node.reentries == 1  # and asked for OFFBOARD again

        other = scaling_fields(ObservationConfig(radius=6.0))  # perception under another
        assert node.act(m.observation(obs, 0.3, 0, 3, scaling=other)) is None
        assert node.refusals == 2 and "SKY_ICO_RADIUS" in node.off_task
        wait_for(lambda: said("SKY_ICO_RADIUS=6 m, trained with 4"), 10.0, "the radius")

        # an actor that records how its observations were made (policy.training.evaluate.
        # ActorController.trained_observation): perception under another face encoding
        node.trained_observation = ObservationConfig()
        prox = scaling_fields(ObservationConfig(encoding="proximity"))
        assert node.act(m.observation(obs, 0.4, 0, 4, scaling=prox)) is None
        assert set(node.off_task) == {"observation"} and node.refusals == 3
        wait_for(lambda: said("Policy off: encoding=proximity, trained with"), 10.0,
                 "the encoding")  # (STATUSTEXT keeps 50 bytes)
        assert node.act(m.observation(obs, 0.5, 0, 5, scaling=scaling)) is not None
    finally:
        stop_all(stop, (thread, sim), (bridge, node, gcs), buses)


def test_a_policy_started_beside_a_crashed_vehicle_joins_once_it_is_placed(tmp_path):
    """A policy (re)started while the vehicle lies crashed and disarmed is denied arming
    until the simulator places the vehicle for the next episode; and the vehicle can come
    down again after its arming, before the node's takeoff or OFFBOARD switch (denied: not
    armed). Both times start() tries again from arming and joins in OFFBOARD, instead of
    exiting (the chaos test's restarted policy did, on each, and the run ran out of
    restarts)."""
    from sitl.commander.machine import State

    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    buses = [Bus.open(cfg) for _ in range(3)]
    api, api_local = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    bridge = BridgeNode(buses[0], "uav1", VehicleLinkConfig(
        api=LinkConfig(api_local, api),
        gcs=LinkConfig(free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)),
        params_file=str(tmp_path / "params.json")))
    stop = threading.Event()
    thread = threading.Thread(target=bridge.run, args=(stop.is_set,), daemon=True)
    commander = Commander()
    commander.place(0.0, True, "OFFBOARD")
    commander.collision(0.0)  # the episode ended in a crash: disarmed, arming refused
    service = VehicleService(buses[1], "uav1", commander, None)
    node = PolicyNode(buses[2], lambda state: np.zeros(4), "uav1",
                      OffboardClientConfig(listen_port=api), trained=TASK)
    placed_at: list[float] = []  # wall times the sim placed the vehicle
    arms: list[float] = []  # vehicle times the node's arming was accepted after a placement
    accept_arming = commander.arm

    def arm(now: float):  # the commander's own verdict, noted
        verdict = accept_arming(now)
        if placed_at and verdict.accepted:
            arms.append(now)
        return verdict

    commander.arm = arm

    def vehicle() -> None:
        """The sim: the next episode places the vehicle (in OFFBOARD, as after a crash in
        OFFBOARD) after 1 s; once the node's arming is accepted, it crashes again (before the
        node's takeoff or switch), and the episode after places it once more 1 s later."""
        t, crashed_at = 0.0, time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            if crashed_at is not None and now > crashed_at + 1.0:
                commander.place(t, True, "OFFBOARD")
                placed_at.append(now)
                crashed_at = None
            elif len(placed_at) == 1 and arms and crashed_at is None:
                commander.collision(t)  # down again, between arming and OFFBOARD
                crashed_at = now
            # the node's zero setpoint, streamed from its start, as the sim hands cmd_vel
            # to the commander (what OFFBOARD needs)
            commander.setpoint(t, 0.0, 0.0, 0.0, 0.0, body=True)
            service.serve(t)
            service.publish_status(0.0, t, force=True)
            t += 0.01  # the vehicle's clock at wall speed (the client streams in wall time)
            time.sleep(0.01)

    sim = threading.Thread(target=vehicle, daemon=True)
    thread.start()
    sim.start()
    try:
        node.start(timeout=15.0)
        assert len(placed_at) == 2 and len(arms) >= 2, (placed_at, arms)
        assert commander.state == State.OFFBOARD
        denials = f"cmd.{mavlink.MAV_CMD_COMPONENT_ARM_DISARM}.{mavlink.MAV_RESULT_DENIED}"
        assert bridge.link.counters[denials] >= 1, bridge.link.counters
    finally:
        stop_all(stop, (thread, sim), (bridge, node), buses)
