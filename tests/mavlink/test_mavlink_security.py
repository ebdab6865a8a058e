"""MAVLink security over real UDP on loopback: signing, allow-list, loopback-only binding.

The vehicle is test_mavlink_link's Rig (a real Commander and VehicleLink on a simulated
clock) with a :class:`LinkSecurity`; the clients are skyloop's OffboardClient and stock
pymavlink (``mavutil.setup_signing``, what MAVProxy uses), so signatures are checked
against an independent implementation in both directions.
"""

from __future__ import annotations

import hashlib
import os
import socket
from collections.abc import Iterator

import pytest

os.environ["MAVLINK20"] = "1"  # before mavutil is imported
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402
from test_mavlink_link import Rig, SimClock, gcs_port, recv  # noqa: E402

from mavlink_bridge.interfaces import VelocityCommand  # noqa: E402
from mavlink_bridge.modes import OFFBOARD  # noqa: E402
from mavlink_bridge.offboard_client import (  # noqa: E402
    CommandTimeout,
    OffboardClient,
    OffboardClientConfig,
)
from mavlink_bridge.security import (  # noqa: E402
    KEY_ENV,
    LinkSecurity,
    SigningMAVLink,
    bind_host,
    key_from_text,
    security_from_args,
    signing_timestamp_now,
)
from mavlink_bridge.transport import UdpEndpoint  # noqa: E402
from mavlink_bridge.vehicle_link import LinkConfig, VehicleLink, VehicleLinkConfig  # noqa: E402
from sitl.commander.machine import State  # noqa: E402

KEY = hashlib.sha256(b"skyloop test key").digest()
OTHER_KEY = hashlib.sha256(b"not the key").digest()


def secure_rig(security: LinkSecurity, api_port: int | None, gcs_port: int,
               clock: SimClock | None = None) -> Rig:
    """test_mavlink_link's Rig with its link rebuilt under ``security``."""
    rig = Rig(api_port, gcs_port, clock)
    rig.link.close()
    cfg = VehicleLinkConfig(api=None if api_port is None else LinkConfig(0, api_port),
                            gcs=LinkConfig(0, gcs_port), security=security,
                            params_file=None)
    rig.link = VehicleLink(rig.commander, cfg, on_setpoint=rig._on_setpoint)
    return rig


def snapshot(rig: Rig) -> tuple:
    c = rig.commander
    return (c.state, c.armed, c.failsafe, len(rig.commands), c._sp, c._last_setpoint_time)


@pytest.fixture
def sink() -> Iterator[int]:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # a GCS port nobody reads
    s.bind(("127.0.0.1", 0))
    yield s.getsockname()[1]
    s.close()


def client_for(rig_clock: SimClock, key: bytes | None, system_id: int = 245) -> OffboardClient:
    sec = LinkSecurity(secret_key=key) if key is not None else None
    return OffboardClient(OffboardClientConfig(listen_port=0, system_id=system_id,
                                               security=sec), clock=rig_clock)


# ------------------------------------------------------------------ signing
def test_signed_client_flies_a_signed_vehicle(sink: int) -> None:
    clock = SimClock()
    client = client_for(clock, KEY)
    rig = secure_rig(LinkSecurity(secret_key=KEY), client.address[1], sink, clock)
    client.spin = rig.tick
    try:
        rig.tick()
        client.wait_heartbeat(timeout=2.0)
        client.arm()
        client.takeoff(2.0)
        assert client.wait(lambda: rig.commander.state == State.HOLD, 10.0)
        client.set_velocity_body(1.0, 0.0, 0.0, 0.0)
        client.start_offboard()
        assert rig.commander.state == State.OFFBOARD and client.mode == OFFBOARD
        assert rig.commands[-1] == VelocityCommand(1.0, 0.0, 0.0, 0.0, True, None)
        c, cc = rig.link.counters, client.endpoint.counters
        assert c["api.rx_signed"] == c["api.rx_msgs"] > 0  # every frame in was signed
        assert c["api.rx_unsigned"] == c["api.rx_bad_signature"] == c["api.rx_replay"] == 0
        assert cc["rx_signed"] == cc["rx_msgs"] > 0  # heartbeats, telemetry, acks signed
        assert cc["rx_unsigned"] == 0
    finally:
        client.close()
        rig.link.close()


@pytest.mark.parametrize("client_key", [None, OTHER_KEY], ids=["unsigned", "wrong_key"])
def test_unsigned_or_wrongly_signed_client_is_refused(sink: int, client_key) -> None:
    clock = SimClock()
    client = client_for(clock, client_key)
    rig = secure_rig(LinkSecurity(secret_key=KEY), client.address[1], sink, clock)
    client.spin = rig.tick
    try:
        rig.tick()
        # A client without the key still sees the vehicle (pymavlink, keyless, does
        # not check signatures); the wrong key does not even see the heartbeat.
        if client_key is None:
            client.wait_heartbeat(timeout=2.0)
        else:
            client.wait(lambda: False, 0.5)
            assert client.vehicle is None and client.endpoint.counters["rx_bad_signature"] > 0
            client.vehicle = client.endpoint.peer = rig.link.address("api")
        before = snapshot(rig)
        client.set_velocity_body(1.0, 0.0, 0.0, 0.0)
        with pytest.raises(CommandTimeout):  # no ACK: refused frames are not answered
            client.arm()
        client.wait(lambda: False, 0.5)  # stream setpoints for a while
        assert snapshot(rig) == before and not rig.commander.armed and rig.commands == []
        c = rig.link.counters
        reason = "api.rx_unsigned" if client_key is None else "api.rx_bad_signature"
        # 3 arm attempts + >= 10 setpoints + heartbeats, all refused, none delivered
        assert c[reason] >= 13 and c["api.rx_msgs"] == 0
        assert c["setpoint.accepted"] == 0 and not any(k.startswith("cmd.") for k in c)
        assert rig.link.received == {}
    finally:
        client.close()
        rig.link.close()


def test_stock_pymavlink_signing_interoperates_and_heartbeat_policy() -> None:
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255,
                                     source_component=190)
    gcs.setup_signing(KEY, sign_outgoing=True)
    rig = secure_rig(LinkSecurity(secret_key=KEY), None, gcs_port(gcs))
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    raw.bind(("127.0.0.1", 0))
    try:
        rig.tick()
        hb = recv(gcs, "HEARTBEAT")
        assert hb.get_signed() and hb.get_link_id() == 0  # verified by stock pymavlink
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                  1, 0, 0, 0, 0, 0, 0)
        rig.tick()
        ack = recv(gcs, "COMMAND_ACK")
        assert ack.get_signed() and ack.result == mavlink.MAV_RESULT_ACCEPTED
        assert rig.commander.armed
        # Unsigned HEARTBEAT: refused (it would move the link's peer); unsigned
        # RADIO_STATUS: accepted as PX4/ArduPilot do, but it does not move the peer.
        enc = mavlink.MAVLink(None, 77, 68)
        dest = rig.link.address("gcs")
        raw.sendto(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(enc), dest)
        raw.sendto(mavlink.MAVLink_radio_status_message(1, 2, 3, 4, 5, 6, 7).pack(enc), dest)
        rig.tick()
        c = rig.link.counters
        assert c["gcs.rx_unsigned"] == 1 and c["gcs.rx_unsigned_accepted"] == 1
        assert rig.link.received["RADIO_STATUS"] == 1 and "HEARTBEAT" not in rig.link.received
        assert rig.link.endpoints["gcs"].peer == gcs.port.getsockname()
    finally:
        raw.close()
        gcs.close()
        rig.link.close()


def test_replay_stale_and_forged_future_timestamp(sink: int) -> None:
    rig = secure_rig(LinkSecurity(secret_key=KEY), None, sink)
    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    attacker.bind(("127.0.0.1", 0))
    dest = rig.link.address("gcs")
    try:
        rig.tick()
        now = signing_timestamp_now()
        gcs = SigningMAVLink(255, 190, LinkSecurity(secret_key=KEY, initial_timestamp=now))
        arm = mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        disarm = mavlink.MAVLink_command_long_message(1, 1, 400, 0, 0, 0, 0, 0, 0, 0, 0)
        # A forged frame (wrong key) from the GCS's stream with a timestamp far in the
        # future must not lock the GCS out (pymavlink as shipped records it first).
        forger = SigningMAVLink(255, 190, LinkSecurity(secret_key=OTHER_KEY,
                                                       initial_timestamp=now + 10**12))
        attacker.sendto(disarm.pack(forger), dest)
        frame = arm.pack(gcs)
        attacker.sendto(frame, dest)
        rig.tick()
        assert rig.commander.armed
        attacker.sendto(disarm.pack(gcs), dest)  # genuine: disarm
        rig.tick()
        assert not rig.commander.armed
        attacker.sendto(frame, dest)  # the recorded arm again: a replay
        rig.tick()
        assert not rig.commander.armed
        old = SigningMAVLink(250, 190, LinkSecurity(secret_key=KEY,
                                                    initial_timestamp=now - 7_000_000))
        attacker.sendto(arm.pack(old), dest)  # a new stream 70 s behind: stale
        rig.tick()
        assert not rig.commander.armed
        c = rig.link.counters
        assert (c["gcs.rx_bad_signature"], c["gcs.rx_replay"], c["gcs.rx_stale_timestamp"],
                c["gcs.rx_signed"]) == (1, 1, 1, 2)
        assert c["cmd.400.0"] == 2  # the two genuine commands, nothing else
    finally:
        attacker.close()
        rig.link.close()


# ------------------------------------------------------------------ allow-list
def test_allow_list_refuses_commands_from_other_systems(sink: int) -> None:
    clock = SimClock()
    client = client_for(clock, None, system_id=245)
    rig = secure_rig(LinkSecurity(allow_sysids=frozenset({245})), client.address[1], sink,
                     clock)
    client.spin = rig.tick
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other.bind(("127.0.0.1", 0))
    try:
        rig.tick()
        client.wait_heartbeat(timeout=2.0)
        api = rig.link.address("api")
        client.arm()  # 245 is listed
        assert rig.commander.armed
        before, peer = snapshot(rig), rig.link.endpoints["api"].peer
        for sysid, comp in ((200, 190), (1, 1), (0, 0)):  # a stranger, ourselves, broadcast
            enc = mavlink.MAVLink(None, sysid, comp)
            for msg in (mavlink.MAVLink_command_long_message(1, 1, 400, 0, 0, 21196, 0, 0, 0,
                                                              0, 0),
                        mavlink.MAVLink_set_position_target_local_ned_message(
                            0, 1, 1, 1, 0x05C7, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0, 0),
                        mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3)):
                other.sendto(msg.pack(enc), api)
        rig.tick()
        c = rig.link.counters
        assert c["api.rx_sysid_not_allowed"] == 4  # commands and setpoints of 200 and 0
        assert c["api.rx_own_id"] == 3  # everything claiming to be the vehicle itself
        assert snapshot(rig) == before and rig.commander.armed  # no forced disarm
        assert rig.link.endpoints["api"].peer == peer  # unlisted heartbeats: no redirect
        assert rig.link.received["HEARTBEAT"] >= 2  # but they are delivered (read-only)
    finally:
        other.close()
        client.close()
        rig.link.close()


def test_allow_list_values() -> None:
    with pytest.raises(ValueError, match="broadcast"):
        LinkSecurity(allow_sysids=frozenset({0, 245}))
    with pytest.raises(ValueError, match="1..255"):
        LinkSecurity(allow_sysids=frozenset({256}))
    with pytest.raises(ValueError, match="32 bytes"):
        LinkSecurity(secret_key=b"short")


# ------------------------------------------------------------------ binding
def test_loopback_by_default_and_exposure_needs_the_flag() -> None:
    with VehicleLink(_Idle(), VehicleLinkConfig(api=LinkConfig(0, 9),
                                                gcs=LinkConfig(0, 9))) as link:
        assert link.address("api")[0] == link.address("gcs")[0] == "127.0.0.1"
    for host in ("0.0.0.0", "", "192.0.2.1"):
        with pytest.raises(ValueError, match="--expose"):
            UdpEndpoint((host, 0), None, 1, 1)
    with pytest.raises(ValueError, match="--expose"):
        VehicleLink(_Idle(), VehicleLinkConfig(api=LinkConfig(0, 9),
                                               gcs=LinkConfig(0, 9, "0.0.0.0")))
    with pytest.raises(ValueError, match="--expose"):
        OffboardClient(OffboardClientConfig(listen_host="0.0.0.0", listen_port=0))
    exposed = UdpEndpoint(("0.0.0.0", 0), None, 1, 1, security=LinkSecurity(expose=True))
    try:
        assert exposed.address[0] == "0.0.0.0"
    finally:
        exposed.close()
    assert (bind_host(False), bind_host(True)) == ("127.0.0.1", "0.0.0.0")


class _Idle:
    """A commander that is never asked anything (binding tests)."""

    state, armed, landed, failsafe = "DISARMED", False, True, False


# ------------------------------------------------------------------ command line
def test_cli_flags_key_file_env_and_passphrase(tmp_path) -> None:
    """The security flags of a node's command line (the bridge's; the policy's are the
    same ``SecurityFlags``) -> ``LinkSecurity``."""
    from skyloop.cli.stack import parse_node

    def flags(argv: list[str]):
        return parse_node(["bridge", *argv])

    default = security_from_args(flags([]), env={})
    assert default == LinkSecurity() and not default.signing and not default.expose
    hexfile = tmp_path / "key.hex"
    hexfile.write_text(KEY.hex() + "\n")
    sec = security_from_args(flags(
        ["--signing-key-file", str(hexfile), "--allow-sysid", "245", "--allow-sysid", "255",
         "--expose"]), env={KEY_ENV: "ignored: the file wins"})
    assert sec.secret_key == KEY and sec.allow_sysids == {245, 255} and sec.expose
    env = security_from_args(flags([]), env={KEY_ENV: "correct horse"})
    assert env.secret_key == hashlib.sha256(b"correct horse").digest()  # MAVProxy's rule
    rawfile = tmp_path / "key.bin"
    rawfile.write_bytes(b"\xff" * 32)
    assert security_from_args(flags(["--signing-key-file", str(rawfile)]),
                              env={}).secret_key == b"\xff" * 32
    assert key_from_text("AB" * 32) == bytes.fromhex("ab" * 32)
    with pytest.raises(ValueError, match="empty"):
        key_from_text("  \n")
    with pytest.raises(SystemExit):
        flags(["--allow-sysid", "x"])


def test_signing_timestamp_follows_the_wall_clock() -> None:
    """A vehicle up for hours has sent far fewer frames than 10 us ticks: its signed
    timestamps must still track the wall clock, or a ground station connecting now
    (stock pymavlink, wall-clock timestamp) refuses the stream as over a minute old."""
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255,
                                     source_component=190)
    gcs.setup_signing(KEY, sign_outgoing=True)
    rig = secure_rig(LinkSecurity(secret_key=KEY), None, gcs_port(gcs))
    try:
        ep = rig.link.endpoints["gcs"]
        ep.mav.signing.timestamp -= 2 * 60 * 100_000  # as if booted long ago
        rig.tick()
        hb = recv(gcs, "HEARTBEAT")
        assert hb.get_signed()
        assert gcs.mav.signing.badsig_count == 0
    finally:
        gcs.close()
        rig.link.close()
