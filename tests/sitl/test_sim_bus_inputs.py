"""The simulator node's bus inputs, in process over real loopback Zenoh with JSBSim:
parameters on ``params`` (applied, or counted as rejected), goals on ``goal`` (the
running episode ends ``aborted``, the next starts where the vehicle is, toward it;
unreachable ones refused and counted), and
commander requests on ``command`` flying a geofence breach into RTL."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from loopback import free_port, wait_for

from bus import keys
from bus import messages as m
from bus.node import Bus
from bus.session import SessionConfig
from sitl.node.node import SimNode, SimNodeConfig


@pytest.fixture
def free_sim():
    """A free-flight sim (real time, on the ground) running in a thread; a test bus."""
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    sim_bus, bus = Bus.open(cfg), Bus.open(cfg)
    events: list = []
    bus.subscribe(keys.EPISODE, "uav1", events.append)
    node = SimNode(sim_bus, SimNodeConfig(free_flight=True, episodes=0, realtime=True,
                                          match_timeout_s=0.1,
                                          params={"SKY_HOLD_LAND_T": 2.0}))
    lines: list[str] = []
    thread = threading.Thread(target=node.run, args=(lines.append,), daemon=True)
    thread.start()
    wait_for(lambda: any(e.event == m.START for e in events), timeout=60.0, what="START")
    yield node, bus, events
    node.stopping.set()
    thread.join(10.0)
    assert not thread.is_alive()
    assert any(line.startswith("SKYLOOP-SUMMARY") for line in lines)
    sim_bus.close()
    bus.close()


def test_parameters_from_the_bus(free_sim) -> None:
    node, bus, _ = free_sim
    assert node.commander.config.hold_before_land == 2.0  # from the config (--param)
    pub = bus.publisher(keys.PARAMS, "uav1")
    assert pub.wait_matched()
    for name, value in (("COM_OF_LOSS_T", 99.0), ("NO_SUCH_PARAM", 1.0),
                        ("MPC_XY_VEL_MAX", float("nan")), ("SKY_ICO_RADIUS", 5.0),
                        ("COM_OF_LOSS_T", 2.5), ("MPC_XY_VEL_MAX", 1.0),
                        ("GF_MAX_HOR_DIST", 25.0), ("SKY_FLIGHT_LVL", 6.0)):
        pub.put(m.parameter(name, value))
    wait_for(lambda: node.commander.config.flight_level == 6.0, what="parameters applied")
    c = node.commander.config
    assert (c.setpoint_timeout, c.rtl_speed, c.geofence) == (2.5, 1.0, 25.0)
    assert node.sim.vehicle.autopilot.max_speed_xy == 1.0
    assert node.service.param_rejects == 3  # out of range, unknown, NaN; perception's ok
    assert node.sim.lidar.config.max_range == 5.5  # SKY_ICO_RADIUS 5: the LiDAR reaches it


def test_goal_from_the_bus_starts_a_new_episode(free_sim) -> None:
    node, bus, events = free_sim
    pub = bus.publisher(keys.GOAL, "uav1")
    assert pub.wait_matched()
    here = node.sim.vehicle.truth.position.copy()
    # Goals no episode could reach are refused, counted, and change nothing.
    for bad in ((np.nan, 0.0, 3.5), (here[0], here[1], 20.0), (here[0], here[1], -5.0)):
        pub.put(m.pose_stamped(np.array(bad), 0.0))
    wait_for(lambda: node.goal_rejects == 3, what="three goals refused")
    assert sum(e.event == m.START for e in events) == 1
    goal = here + np.array([10.0, -5.0, 3.5])
    pub.put(m.pose_stamped(goal, 0.0))
    wait_for(lambda: sum(e.event == m.START for e in events) == 2, what="a second START")
    end = next(e for e in events if e.event == m.END)
    assert m.outcome_name(end) == "aborted" and end.episode == 0
    start = [e for e in events if e.event == m.START][1]
    assert start.episode == 1
    assert (start.goal.x, start.goal.y, start.goal.z) == tuple(goal)
    assert np.linalg.norm(np.array([start.start.x, start.start.y, start.start.z]) - here) < 0.2
    assert node.results[0]["outcome"] == "aborted"


def test_geofence_rtl_under_jsbsim(free_sim) -> None:
    """Arm and take off by bus requests, fly OFFBOARD east on cmd_vel (as the bridge
    forwards them) past a 3 m geofence: RTL climbs, flies home, lands, disarms."""
    node, bus, _ = free_sim
    states: list[str] = []
    texts: list[str] = []

    def on_status(msg) -> None:
        if not states or states[-1] != msg.state:
            states.append(str(msg.state))
        texts.extend(msg.event_texts)

    bus.subscribe(keys.STATUS, "uav1", on_status)
    params, cmds = bus.publisher(keys.PARAMS, "uav1"), bus.publisher(keys.CMD_VEL, "uav1")
    assert params.wait_matched() and cmds.wait_matched()
    params.put(m.parameter("GF_MAX_HOR_DIST", 3.0))
    wait_for(lambda: node.commander.config.geofence == 3.0, what="geofence set")

    def request(command: str, mode: str = "") -> bool:
        ack = bus.query(keys.COMMAND, "uav1", m.vehicle_command(command, mode),
                        m.COMMAND_ACK, timeout=2.0)
        return ack is not None and bool(ack.accepted)

    assert request("arm") and request("takeoff")
    wait_for(lambda: node.commander.state == "HOLD", timeout=30.0, what="takeoff done")
    home = node.sim.vehicle.truth.position.copy()
    t = [100.0]

    def stream(seconds: float) -> None:  # 1 m/s east, world frame, 10 Hz
        for _ in range(int(seconds * 10)):
            t[0] += 0.1
            cmds.put(m.velocity_setpoint((1.0, 0.0, 0.0), 0.0, t[0], body=False))
            threading.Event().wait(0.1)

    stream(1.0)
    assert request("set_mode", "OFFBOARD")
    stream(8.0)
    wait_for(lambda: node.commander.state == "RTL", timeout=10.0, what="geofence RTL")
    assert node.commander.failsafe_reason == "geofence"
    wait_for(lambda: node.commander.state == "DISARMED", timeout=60.0, what="RTL landed")
    here = node.sim.vehicle.truth.position
    assert np.hypot(*(here - home)[:2]) < 1.0  # home (within the arrival radius + drift)
    assert node.commander.landed and not node.commander.crashed
    wait_for(lambda: "Landed home, disarmed" in texts, what="status events")
    assert states[-3:] == ["OFFBOARD", "RTL", "DISARMED"], states
    assert "Failsafe: geofence, returning home" in texts


def test_free_flight_episode_ends_at_its_goal(free_sim) -> None:
    """A goal where the vehicle stands is reached at once: success, and the next episode
    heads for the next seeded goal (free flight: no timeout, no placement)."""
    node, bus, events = free_sim
    pub = bus.publisher(keys.GOAL, "uav1")
    assert pub.wait_matched()
    pub.put(m.pose_stamped(node.sim.vehicle.truth.position.copy(), 0.0))
    wait_for(lambda: sum(e.event == m.START for e in events) == 3, what="a third START")
    outcomes = [m.outcome_name(e) for e in events if e.event == m.END]
    assert outcomes[:2] == ["aborted", "success"]
    third = [e for e in events if e.event == m.START][2]
    seeded = node.sim.world.sample_start_goal(np.random.default_rng(node.config.seed + 2))[1]
    assert (third.goal.x, third.goal.y, third.goal.z) == tuple(seeded)
    assert node.commander.state == "DISARMED"  # it never moved: still on the ground


def test_offboard_request_served_right_behind_its_setpoint() -> None:
    """MAVSDK's "set a setpoint, then ``offboard.start()``": the bridge forwards both in
    that order, but the sim can find the request queued before the setpoint is offered
    (a query is queued natively, a ``cmd_vel`` waits for a Python callback). Here the
    setpoint waits in the node's inbox, not yet offered, when the request is served: the
    request takes it first (``VehicleService.take_setpoints``), OFFBOARD is accepted."""
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    sim_bus, bus = Bus.open(cfg), Bus.open(cfg)
    try:
        node = SimNode(sim_bus, SimNodeConfig(free_flight=True, realtime=True))
        node.commander.reset(node.now(), airborne=True)  # flying, in HOLD
        cmds = bus.publisher(keys.CMD_VEL, "uav1")
        assert cmds.wait_matched()
        cmds.put(m.velocity_setpoint((1.0, 0.0, 0.0), 0.0, 0.0, body=False))
        wait_for(lambda: len(node.cmds) == 1, what="the setpoint in the node's inbox")
        assert not node.commander.offboard_available(node.now())  # not offered yet
        answers: list = []
        asker = threading.Thread(target=lambda: answers.append(bus.query(
            keys.COMMAND, "uav1", m.vehicle_command("set_mode", "OFFBOARD"), m.COMMAND_ACK,
            timeout=5.0)))
        asker.start()
        wait_for(lambda: node.service.serve(node.now()) == 1, what="the request served")
        asker.join(5.0)
        assert answers[0] is not None and answers[0].accepted, answers
        assert node.commander.state == "OFFBOARD" and len(node.cmds) == 0
    finally:
        sim_bus.close()
        bus.close()


def test_the_node_leaves_its_callers_config_as_given() -> None:
    """Goals from the bus imply free flight in real time: the node derives that for itself
    and does not rewrite the config it was given (a caller may reuse it)."""
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    sim_bus = Bus.open(cfg)
    try:
        given = SimNodeConfig(goals_from_bus=True, scenario="forest")
        node = SimNode(sim_bus, given)
        assert node.config.free_flight and node.config.realtime
        assert node.config.episode.scenario == "forest"
        assert not given.free_flight and not given.realtime
        assert given.episode.scenario == SimNodeConfig().episode.scenario
    finally:
        sim_bus.close()
