"""bus.session and bus.node over real Zenoh on loopback (multicast scouting off): the
hub election, gossip between peers, a 345 KB scan with BLOCK, client-router-client
through a Python router, undecodable payloads counted, SessionConfig.from_env."""

from __future__ import annotations

import socket
import threading

import numpy as np
import pytest
from loopback import free_port, wait_for

from bus import keys
from bus import messages as m
from bus.node import Bus
from bus.session import (
    SessionConfig,
    open_router,
    open_session,
    run_router,
)


def port_bound(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0



@pytest.fixture
def hub_cfg():
    return SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")


@pytest.fixture
def buses():
    opened: list[Bus] = []

    def make(cfg):
        bus = Bus.open(cfg)
        opened.append(bus)
        return bus

    yield make
    for bus in reversed(opened):
        bus.close()


def test_peers_meet_through_the_hub(hub_cfg, buses):
    port = int(hub_cfg.hub.rsplit(":", 1)[1])
    assert hub_cfg.uses_hub and not port_bound(port)
    a = buses(hub_cfg)
    assert port_bound(port)  # the first session claimed the hub
    b = buses(hub_cfg)  # the second found it taken and joined
    inbox = b.inbox(keys.CMD_VEL, "uav1")
    pub = a.publisher(keys.CMD_VEL, "uav1")
    assert pub.wait_matched(5.0)
    for i in range(5):
        pub.put(m.velocity_setpoint((i, 0.0, 0.0), 0.5, 0.1 * i, body=False))
    got = [m.setpoint_values(inbox.get(timeout=5.0)) for _ in range(5)]
    assert got == [(float(i), 0.0, 0.0, 0.5) for i in range(5)]
    assert a.counters()["published"] == 5 and b.counters()["received"] == 5


def test_gossip_peers_survive_the_hub(hub_cfg, buses):
    hub = Bus.open(hub_cfg)
    b, c = buses(hub_cfg), buses(hub_cfg)
    wait_for(lambda: len(list(b.session.info.peers_zid())) >= 2, what="b meshed with c")
    inbox = c.inbox(keys.ODOM, "uav1")
    pub = b.publisher(keys.ODOM, "uav1")
    assert pub.wait_matched(5.0)
    hub.close()  # b and c stay connected directly (gossip), not through the hub
    pub.put(m.odometry((1, 2, 3), (0, 0, 0), (0, 0, 0, 1), 1.0))
    pos, _, _ = m.odometry_values(inbox.get(timeout=5.0))
    np.testing.assert_array_equal(pos, [1, 2, 3])


def test_full_scan_arrives_with_block(hub_cfg, buses):
    a, b = buses(hub_cfg), buses(hub_cfg)
    inbox = b.inbox(keys.LIDAR_POINTS, "uav1", maxsize=64)
    pub = a.publisher(keys.LIDAR_POINTS, "uav1")
    assert pub.wait_matched(5.0)
    rng = np.random.default_rng(0)
    scans = [rng.normal(size=(28_800, 3)).astype(np.float32) for _ in range(3)]
    for i in range(30):  # back to back, faster than a VLP-16: nothing may be lost
        assert pub.put(m.pointcloud(scans[i % 3], 0.1 * i)) > 345_000
    for i in range(30):
        msg = inbox.get(timeout=10.0)
        assert m.seconds(msg.header.stamp) == pytest.approx(0.1 * i)
        np.testing.assert_array_equal(m.points_from_pointcloud(msg), scans[i % 3])
    assert inbox.counters()["dropped"] == 0


def test_client_router_client():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    cfg = SessionConfig(mode="client", connect=(endpoint,), connect_timeout_s=5.0)
    a, b = Bus.open(cfg), Bus.open(cfg)
    try:
        inbox = b.inbox(keys.EPISODE, "*", with_vehicle=True)
        pub = a.publisher(keys.EPISODE, "uav7")
        assert pub.wait_matched(5.0)
        pub.put(m.episode_start(1, 99, (0, 0, 1), (5, 5, 1), 0.0))
        vehicle, msg = inbox.get(timeout=5.0)
        assert vehicle == "uav7" and msg.seed == 99
    finally:
        a.close()
        b.close()
        router.close()


def test_run_router_until_stopped():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stop = threading.Event()
    thread = threading.Thread(target=run_router, args=(endpoint, stop), daemon=True)
    thread.start()
    cfg = SessionConfig(mode="client", connect=(endpoint,), connect_timeout_s=5.0)
    with Bus.open(cfg) as a, Bus.open(cfg) as b:
        got = []
        b.subscribe(keys.GOAL, "uav1", got.append)
        pub = a.publisher(keys.GOAL, "uav1")
        assert pub.wait_matched(5.0)
        pub.put(m.pose_stamped((3, 4, 5), 0.0))
        wait_for(lambda: got, what="goal via the router")
    stop.set()
    thread.join(5.0)
    assert not thread.is_alive()
    from skyloop.cli.tools import parse_tool

    with pytest.raises(SystemExit) as exc:  # the 'skyloop router' command
        parse_tool(["router", "--help"])
    assert exc.value.code == 0


def test_malformed_payload_is_counted_not_raised(hub_cfg, buses):
    a, b = buses(hub_cfg), buses(hub_cfg)
    got, calls = [], []
    sub = b.subscribe(keys.CMD_VEL, "uav1", got.append)

    def flaky(msg):
        calls.append(msg)
        raise RuntimeError("user callback bug")

    bad_cb = b.subscribe(keys.CMD_VEL, "uav1", flaky)
    pub = a.publisher(keys.CMD_VEL, "uav1")
    assert pub.wait_matched(5.0)
    pub.put_bytes(b"definitely not CDR")
    pub.put_bytes(m.encode(m.odometry((0, 0, 0), (0, 0, 0), (0, 0, 0, 1), 0.0))[:20])
    # the stream goes on after bad payloads
    pub.put(m.velocity_setpoint((1, 2, 3), 4, 0.0, body=False))
    wait_for(lambda: len(got) == 1 and len(calls) == 1, what="the good message")
    assert m.setpoint_values(got[0]) == (1, 2, 3, 4)
    assert sub.counters() == {"received": 1, "decode_errors": 2, "callback_errors": 0}
    assert bad_cb.counters() == {"received": 1, "decode_errors": 2, "callback_errors": 1}
    assert b.counters()["decode_errors"] == 4
    with pytest.raises(TypeError):  # the publisher refuses a message of the wrong type
        pub.put(m.pose_stamped((0, 0, 0), 0.0))


def test_inbox_drops_oldest_and_counts(hub_cfg, buses):
    a, b = buses(hub_cfg), buses(hub_cfg)
    inbox = b.inbox(keys.CLOCK, "uav1", maxsize=2)
    pub = a.publisher(keys.CLOCK, "uav1")
    assert pub.wait_matched(5.0)
    for i in range(5):
        pub.put(m.step_clock(i, 0.1 * i))
    wait_for(lambda: inbox.counters()["received"] == 5, what="5 clocks")
    assert [inbox.get(timeout=1).step for _ in range(2)] == [3, 4]
    assert inbox.counters()["dropped"] == 3
    assert inbox.get_nowait() is None
    with pytest.raises(TimeoutError):
        inbox.get(timeout=0.01)


def test_close_is_idempotent_and_final(hub_cfg):
    bus = Bus.open(hub_cfg)
    pub = bus.publisher(keys.ODOM, "uav1")
    bus.close()
    bus.close()
    assert bus.session.is_closed()
    with pytest.raises(RuntimeError):
        pub.put_bytes(b"x")
    with pytest.raises(RuntimeError):
        bus.publisher(keys.ODOM, "uav1")


def test_explicit_endpoints_skip_the_hub():
    port = free_port()
    listener = open_session(SessionConfig(listen=(f"tcp/127.0.0.1:{port}",)))
    try:
        joined = open_session(SessionConfig(connect=(f"tcp/127.0.0.1:{port}",)))
        try:
            wait_for(lambda: list(joined.info.peers_zid()), what="explicit connect")
        finally:
            joined.close()
    finally:
        listener.close()


def test_session_config_from_env():
    cfg = SessionConfig.from_env({})
    assert (cfg.mode, cfg.listen, cfg.connect, cfg.multicast_scouting) == ("peer", (), (), False)
    assert cfg.uses_hub and cfg.hub == "tcp/127.0.0.1:7447"
    cfg = SessionConfig.from_env({"SKYLOOP_ZENOH_MODE": "client",
                                  "SKYLOOP_ZENOH_CONNECT": "tcp/10.0.0.2:7447, tcp/10.0.0.3:7447"})
    assert cfg.mode == "client" and cfg.connect == ("tcp/10.0.0.2:7447", "tcp/10.0.0.3:7447")
    assert not cfg.uses_hub
    cfg = SessionConfig.from_env({"SKYLOOP_ZENOH_MODE": " Router ",
                                  "SKYLOOP_ZENOH_LISTEN": "tcp/0.0.0.0:7447"})
    assert (cfg.mode, cfg.listen) == ("router", ("tcp/0.0.0.0:7447",))
    cfg = SessionConfig.from_env({"SKYLOOP_ZENOH_HUB": "tcp/127.0.0.1:17000"},
                                 multicast_scouting=True)
    assert cfg.hub == "tcp/127.0.0.1:17000" and cfg.multicast_scouting
    client = SessionConfig(mode="client")
    assert '"tcp/127.0.0.1:7447"' in client.zenoh_config().get_json("connect/endpoints")
    assert client.zenoh_config().get_json("scouting/multicast/enabled") == "false"
    with pytest.raises(ValueError):
        SessionConfig.from_env({"SKYLOOP_ZENOH_MODE": "bogus"})
    with pytest.raises(ValueError):
        SessionConfig(mode="client", listen=("tcp/127.0.0.1:1",))


def test_readiness_tokens_come_and_go(hub_cfg, buses):
    """A node's readiness is a liveliness token: a watcher sees the ones declared before
    it started (history) and after, and sees a node go when its bus closes."""
    watcher, early, late = buses(hub_cfg), Bus.open(hub_cfg), Bus.open(hub_cfg)
    seen: list[tuple[str, bool]] = []
    try:
        early.declare_ready("uav1", "record")
        watcher.watch_ready("*", lambda node, alive: seen.append((node, alive)))
        wait_for(lambda: ("record", True) in seen, what="the token declared before")
        late.declare_ready("uav1", "sim")
        wait_for(lambda: ("sim", True) in seen, what="the token declared after")
        late.close()
        wait_for(lambda: ("sim", False) in seen, what="the node gone")
        assert ("record", False) not in seen
        with pytest.raises(ValueError, match="node name"):
            early.declare_ready("uav1", "Bad/Name")
    finally:
        early.close()
        late.close()
    assert keys.ready_key("uav1", "sim") == "skyloop/uav1/ready/sim"


def test_close_undeclares_everything_through_a_ctrl_c(hub_cfg):
    """A KeyboardInterrupt while closing one entity still undeclares the others (their
    callback threads would keep the process alive) and is raised again afterwards."""
    bus = Bus.open(hub_cfg)
    sub = bus.subscribe(keys.EPISODE, "uav1", lambda msg: None)

    class Interrupted:
        def close(self) -> None:
            raise KeyboardInterrupt

    bus._track(Interrupted())  # closed first (reverse order), then the subscription
    with pytest.raises(KeyboardInterrupt):
        bus.close()
    assert sub._sub is None  # undeclared all the same
