"""The vehicle's MAVLink endpoint over real UDP on loopback, pymavlink on both ends.

A `Rig` runs a Commander, a kinematic point vehicle and a VehicleLink on a simulated
clock; the offboard client and a pymavlink "ground station" talk to it over UDP. Ports
are the OS's free ephemeral ports (bind to 0). Loopback UDP delivers a datagram into
the receiver's queue before ``sendto`` returns, so ticking the rig after a send is
enough: no sleeps.
"""

from __future__ import annotations

import math
import os
import random
import socket
import struct
from collections.abc import Iterator

import pytest

os.environ["MAVLINK20"] = "1"  # before mavutil is imported
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from mavlink_bridge.interfaces import VehicleTelemetry, VelocityCommand  # noqa: E402
from mavlink_bridge.modes import (  # noqa: E402
    AUTO_LAND,
    AUTO_LOITER,
    OFFBOARD,
    Px4Mode,
    encode_custom_mode,
)
from mavlink_bridge.offboard_client import (  # noqa: E402
    CommandRejected,
    CommandTimeout,
    OffboardClient,
    OffboardClientConfig,
)
from mavlink_bridge.vehicle_link import LinkConfig, VehicleLink, VehicleLinkConfig  # noqa: E402
from sitl.commander.machine import Commander, State, VehicleSample  # noqa: E402

mavutil.set_dialect("common")
DT = 0.02


def f32(x: float) -> float:
    return struct.unpack("<f", struct.pack("<f", x))[0]


class SimClock:
    """Simulated time, k * DT."""

    def __init__(self) -> None:
        self.k = 0

    def __call__(self) -> float:
        return self.k * DT


class Rig:
    """Commander + point vehicle + VehicleLink, advanced by `tick` on a simulated clock."""

    def __init__(self, api_port: int | None, gcs_port: int,
                 clock: SimClock | None = None) -> None:
        self.clock = clock or SimClock()
        self.commander = Commander()
        self.z = self.vz = self.yaw = 0.0
        self.commands: list[VelocityCommand] = []
        cfg = VehicleLinkConfig(api=None if api_port is None else LinkConfig(0, api_port),
                                gcs=LinkConfig(0, gcs_port))
        self.link = VehicleLink(self.commander, cfg, on_setpoint=self._on_setpoint)

    @property
    def now(self) -> float:
        return self.clock()

    def _on_setpoint(self, cmd: VelocityCommand, now: float, time_boot_ms: int = 0) -> None:
        self.commands.append(cmd)
        self.commander.setpoint(now, cmd.vx, cmd.vy, cmd.vz, cmd.yaw_rate,
                                body=cmd.frame_is_body, yaw=cmd.yaw)

    def tick(self) -> None:
        self.clock.k += 1
        t = self.now
        self.link.poll(t)
        out = self.commander.step(t, VehicleSample(self.z, self.vz, self.yaw, self.z))
        self.vz = out.vz if self.commander.armed else 0.0
        self.z = max(0.0, self.z + self.vz * DT)
        if self.z == 0.0:  # on the ground
            self.vz = max(0.0, self.vz)
        self.yaw += out.yaw_rate * DT
        self.link.update_telemetry(VehicleTelemetry(t, (1.0, 2.0, self.z), (0.0, 0.0, self.vz),
                                                    (0.1, 0.2, self.yaw), (0.01, 0.02, 0.03)))
        for e in self.commander.pop_events():
            self.link.statustext(e.text, e.severity)


@pytest.fixture
def gcs() -> Iterator[mavutil.mavfile]:
    conn = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255,
                                      source_component=190)
    yield conn
    conn.close()


@pytest.fixture
def client_and_rig() -> Iterator[tuple[OffboardClient, Rig]]:
    clock = SimClock()
    client = OffboardClient(OffboardClientConfig(listen_port=0), clock=clock)
    gcs_sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # a GCS port nobody reads
    gcs_sink.bind(("127.0.0.1", 0))
    rig = Rig(client.address[1], gcs_sink.getsockname()[1], clock)
    client.spin = rig.tick
    yield client, rig
    client.close()
    rig.link.close()
    gcs_sink.close()


def gcs_port(conn: mavutil.mavfile) -> int:
    return conn.port.getsockname()[1]


def recv(conn: mavutil.mavfile, kind: str) -> object:
    m = conn.recv_match(type=kind, blocking=True, timeout=2.0)
    assert m is not None, f"no {kind}"
    return m


# ------------------------------------------------------------------ ground station
def test_gcs_sees_px4_heartbeat_commands_and_telemetry(gcs: mavutil.mavfile) -> None:
    rig = Rig(api_port=None, gcs_port=gcs_port(gcs))  # GCS link only
    try:
        rig.tick()
        hb = recv(gcs, "HEARTBEAT")
        assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 1)
        assert hb.type == mavlink.MAV_TYPE_QUADROTOR
        assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
        assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        assert hb.custom_mode == AUTO_LOITER.custom_mode == encode_custom_mode(4, 3)
        assert hb.system_status == mavlink.MAV_STATE_STANDBY
        assert gcs.mavlink20() and hb.get_header().mlen > 0
        rig.tick()  # telemetry set by the first tick goes out at the next poll
        pos = recv(gcs, "LOCAL_POSITION_NED")  # ENU (1, 2, z) -> NED (2, 1, -z)
        assert (pos.x, pos.y, pos.z) == (2.0, 1.0, 0.0)
        att = recv(gcs, "ATTITUDE")
        assert att.roll == pytest.approx(0.1) and att.pitch == pytest.approx(-0.2)
        assert att.yaw == pytest.approx(math.pi / 2) and att.yawspeed == pytest.approx(-0.03)
        # Arm from the GCS: ACK, then a heartbeat showing armed at once.
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                  1, 0, 0, 0, 0, 0, 0)
        rig.tick()
        ack = recv(gcs, "COMMAND_ACK")
        assert (ack.command, ack.result) == (400, mavlink.MAV_RESULT_ACCEPTED)
        assert (ack.target_system, ack.target_component) == (255, 190)
        assert recv(gcs, "HEARTBEAT").base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        assert recv(gcs, "STATUSTEXT").text == "Armed"
        # Mode changes through DO_SET_MODE with PX4 custom modes.
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 4, 2, 0, 0, 0, 0)
        rig.tick()
        assert recv(gcs, "COMMAND_ACK").result == mavlink.MAV_RESULT_ACCEPTED
        assert recv(gcs, "HEARTBEAT").custom_mode == encode_custom_mode(4, 2)  # AUTO.TAKEOFF
        for mode, result in (((3, 0), mavlink.MAV_RESULT_UNSUPPORTED),  # POSCTL
                             ((6, 0), mavlink.MAV_RESULT_TEMPORARILY_REJECTED)):  # no stream
            gcs.mav.command_long_send(1, 1, 176, 0, 1, *mode, 0, 0, 0, 0)
            rig.tick()
            assert recv(gcs, "COMMAND_ACK").result == result
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH, 0, 0, 0, 0, 0,
                                  0, 0, 0)
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_SERVO, 0, 1, 1500, 0, 0,
                                  0, 0, 0)
        rig.tick()
        assert recv(gcs, "COMMAND_ACK").result == mavlink.MAV_RESULT_ACCEPTED  # RTL, in air
        assert recv(gcs, "COMMAND_ACK").result == mavlink.MAV_RESULT_UNSUPPORTED
        # mavutil's PX4 helper works as it does against PX4 SITL.
        gcs.target_system, gcs.target_component = 1, 1
        gcs.set_mode_px4(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, 6)  # AUTO.LAND
        rig.tick()
        assert recv(gcs, "COMMAND_ACK").result == mavlink.MAV_RESULT_ACCEPTED
        assert rig.commander.state == State.LAND
        assert recv(gcs, "HEARTBEAT").custom_mode == AUTO_LAND.custom_mode
    finally:
        rig.link.close()


def test_set_mode_message_changes_mode_as_qgroundcontrol_sends_it(
        gcs: mavutil.mavfile) -> None:
    """QGroundControl changes PX4 modes with SET_MODE (11): base_mode from the last
    heartbeat with CUSTOM_MODE_ENABLED, custom_mode the whole PX4 value; no ACK."""
    rig = Rig(api_port=None, gcs_port=gcs_port(gcs))
    try:
        rig.tick()
        recv(gcs, "HEARTBEAT")
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                  1, 0, 0, 0, 0, 0, 0)
        rig.tick()
        assert recv(gcs, "COMMAND_ACK").result == mavlink.MAV_RESULT_ACCEPTED
        armed_custom = mavlink.MAV_MODE_FLAG_SAFETY_ARMED | 1
        takeoff = encode_custom_mode(4, 2)
        gcs.mav.set_mode_send(1, armed_custom, takeoff)
        rig.tick()
        assert rig.commander.state == State.TAKEOFF
        while (hb := recv(gcs, "HEARTBEAT")).custom_mode != takeoff:
            pass
        for target, base, custom in ((1, 0x80, AUTO_LAND.custom_mode),  # no custom flag
                                     (1, armed_custom, encode_custom_mode(3)),  # POSCTL
                                     (2, armed_custom, AUTO_LAND.custom_mode)):  # not us
            gcs.mav.set_mode_send(target, base, custom)
            rig.tick()
            assert rig.commander.state == State.TAKEOFF
        gcs.mav.set_mode_send(1, armed_custom, AUTO_LAND.custom_mode)
        rig.tick()
        assert rig.commander.state == State.LAND and rig.commander.armed
        while (hb := recv(gcs, "HEARTBEAT")).custom_mode != AUTO_LAND.custom_mode:
            pass
        assert gcs.recv_match(type="COMMAND_ACK", blocking=False) is None  # never acked
        c = rig.link.counters
        assert (c["set_mode.0"], c["set_mode.3"], c["set_mode.other_target"]) == (2, 2, 1)
        assert hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    finally:
        rig.link.close()


def test_link_answers_whoever_spoke_from_its_fixed_port(gcs: mavutil.mavfile) -> None:
    rig = Rig(api_port=None, gcs_port=gcs_port(gcs))
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # a second GCS elsewhere
    other.bind(("127.0.0.1", 0))
    other.settimeout(2.0)
    try:
        rig.tick()
        recv(gcs, "HEARTBEAT")
        enc = mavlink.MAVLink(None, 200, 190)
        cmd = mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
        other.sendto(cmd.pack(enc), rig.link.address("gcs"))
        rig.tick()
        dec = mavlink.MAVLink(None)
        data, src = other.recvfrom(65535)
        assert src == rig.link.address("gcs")  # sent from the link's own bound port
        got = dec.parse_buffer(data)
        assert got[0].get_type() == "COMMAND_ACK" and got[0].target_system == 200
        for _ in range(60):  # the next heartbeats follow the new partner
            rig.tick()
        types = {m.get_type() for m in dec.parse_buffer(other.recvfrom(65535)[0])}
        assert types & {"HEARTBEAT", "LOCAL_POSITION_NED", "ATTITUDE", "STATUSTEXT"}
    finally:
        other.close()
        rig.link.close()


# ------------------------------------------------------------------ offboard client
def test_offboard_client_arm_takeoff_offboard_failsafe_land(client_and_rig) -> None:
    client, rig = client_and_rig
    rig.tick()
    client.wait_heartbeat(timeout=2.0)
    assert client.vehicle == rig.link.address("api") and client.mode == AUTO_LOITER
    with pytest.raises(CommandRejected) as err:  # offboard needs a stream and arming
        client.set_mode(OFFBOARD)
    assert err.value.result == mavlink.MAV_RESULT_DENIED
    client.arm()
    assert client.wait(lambda: client.armed, 1.0)
    client.takeoff(2.0)
    assert client.wait(lambda: client.mode == AUTO_LOITER, 10.0)  # takeoff done: Hold
    assert rig.commander.state == State.HOLD and rig.z == pytest.approx(2.0, abs=0.11)
    assert client.local_position.z == pytest.approx(-rig.z, abs=0.1)
    # Offboard: stream first, then the switch; the heartbeat shows main mode 6.
    client.set_velocity_body(1.0, 0.0, 0.1, 0.1)
    client.start_offboard()
    assert client.mode == OFFBOARD and rig.commander.state == State.OFFBOARD
    n = len(rig.commands)
    client.wait(lambda: False, 1.0)  # 1 s of flight at 20 Hz re-sends
    assert 19 <= len(rig.commands) - n <= 21
    assert rig.commands[-1] == VelocityCommand(1.0, 0.0, f32(0.1), f32(0.1), True, None)
    client.set_velocity_enu(0.5, -0.5, 0.0, 0.0)
    client.poll()
    rig.tick()
    assert rig.commands[-1] == VelocityCommand(0.5, -0.5, 0.0, 0.0, False, None)
    # Setpoint loss: hold (failsafe, CRITICAL) after 1 s, then land and disarm.
    client.stop_stream()
    t0 = rig.now
    assert client.wait(lambda: client.mode == AUTO_LOITER, 2.0)
    assert rig.now - t0 == pytest.approx(1.0 + DT, abs=1.5 * DT)
    assert client.system_status == mavlink.MAV_STATE_CRITICAL
    assert client.wait(lambda: client.mode == AUTO_LAND, 6.0)
    assert client.wait(lambda: not client.armed, 10.0)
    texts = [t for _, t in client.statustexts]
    assert "Failsafe: setpoints lost, holding" in texts and texts[-1] == "Landed, disarmed"
    assert rig.link.counters["setpoint.accepted"] == len(rig.commands)


def test_offboard_client_land_and_unsupported(client_and_rig) -> None:
    client, rig = client_and_rig
    rig.tick()
    client.wait_heartbeat(timeout=2.0)
    with pytest.raises(CommandRejected) as err:
        client.land()  # not armed
    assert err.value.result == mavlink.MAV_RESULT_DENIED
    with pytest.raises(CommandRejected) as err:
        client.set_mode(Px4Mode(1, 0))  # MANUAL
    assert err.value.result == mavlink.MAV_RESULT_UNSUPPORTED
    with pytest.raises(Exception, match="set a setpoint"):
        client.start_offboard()
    client.arm()
    client.takeoff()
    client.wait(lambda: rig.z > 1.0, 5.0)
    client.land()
    assert client.wait(lambda: not client.armed, 10.0)
    assert rig.commander.state == State.DISARMED


def test_command_timeout_when_the_vehicle_is_silent(client_and_rig) -> None:
    client, rig = client_and_rig
    rig.tick()
    client.wait_heartbeat(timeout=2.0)
    client.spin = lambda: setattr(rig.clock, "k", rig.clock.k + 1)  # time passes, nobody answers
    with pytest.raises(CommandTimeout):
        client.arm()
    assert not rig.commander.armed


# ------------------------------------------------------------------ bad input
def test_bad_setpoints_and_garbage_are_counted_never_applied(client_and_rig) -> None:
    client, rig = client_and_rig
    rig.tick()
    client.wait_heartbeat(timeout=2.0)
    dest = rig.link.address("api")
    sock, enc = client.endpoint.sock, mavlink.MAVLink(None, 245, 190)

    def setpoint(frame: int = 1, v: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 yaw_rate: float = 0.0, target: int = 1) -> bytes:
        return mavlink.MAVLink_set_position_target_local_ned_message(
            0, target, 1, frame, 0x05C7, 0, 0, 0, *v, 0, 0, 0, 0, yaw_rate).pack(enc)

    good = setpoint(v=(1.0, 0.0, 0.0))
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    unknown = bytearray(mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 0, 3).pack(enc))
    unknown[7:10] = (0x39, 0x30, 0x00)  # message id 12345
    frames_sent = [
        setpoint(v=(math.nan, 0.0, 0.0)), setpoint(v=(0.0, math.inf, 0.0)),
        setpoint(yaw_rate=-math.inf), setpoint(frame=7), setpoint(frame=255),
        setpoint(v=(50.0, 0.0, 0.0)), setpoint(target=9),
        bytes(bad_crc), good[:15], bytes(unknown), b"\x00\x01garbage\xff" * 5,
        bytes(range(256)), b"\xfd", b"",
        mavlink.MAVLink_command_long_message(1, 1, 400, 0, math.nan, 0, 0, 0, 0, 0,
                                             0).pack(enc),
        mavlink.MAVLink_command_long_message(1, 1, 176, 0, math.inf, 6, 0, 0, 0, 0,
                                             0).pack(enc),
        mavlink.MAVLink_command_long_message(7, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(enc),
    ]
    for data in frames_sent:
        sock.sendto(data, dest)
    rig.tick()
    c = rig.link.counters
    assert rig.commands == [] and not rig.commander.armed
    assert c["setpoint.nan"] == 1 and c["setpoint.inf"] == 2
    assert c["setpoint.unknown_frame"] == 2 and c["setpoint.out_of_range"] == 1
    assert c["setpoint.wrong_target"] == 1 and c["setpoint.accepted"] == 0
    assert c["api.rx_bad_crc"] == 1 and c["api.rx_unknown_msg_id"] == 1
    # truncated: good[:15], b"\xfd", and range(256) once its 0xFD starts a frame
    assert c["api.rx_truncated"] == 3 and c["api.rx_bad_prefix"] == 2
    assert c["api.rx_datagrams"] == len(frames_sent) + 1  # + the client's heartbeat
    assert c["cmd.other_target"] == 1 and c["cmd.400.2"] == 1 and c["cmd.176.2"] == 1
    assert c["handler_error"] == 0
    # Still alive and answering.
    sock.sendto(good, dest)
    client.arm()
    assert rig.commander.armed and len(rig.commands) == 1


def test_seeded_fuzz_never_raises_and_delivers_only_valid_setpoints() -> None:
    """2,000 random and mutated frames (issue 5 scales this up): nothing escapes poll()."""
    rng = random.Random(1)
    rig = Rig(api_port=9, gcs_port=9)  # discard port: nobody listens
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    enc = mavlink.MAVLink(None, 245, 190)
    specials = [math.nan, math.inf, -math.inf, 0.0, 1.0, -1.0, 1e38, 6.0, 4.0]

    def rf() -> float:
        return rng.choice(specials) if rng.random() < 0.5 else rng.uniform(-100.0, 100.0)

    makers = [
        lambda: mavlink.MAVLink_set_position_target_local_ned_message(
            0, rng.choice([0, 1, 2]), rng.choice([0, 1]), rng.randrange(30),
            rng.choice([0x5C7, 0x9C7, 0xDC7, rng.randrange(65536)]), *[rf() for _ in range(11)]),
        lambda: mavlink.MAVLink_command_long_message(
            rng.choice([1, 2]), rng.choice([0, 1]),
            rng.choice([400, 22, 21, 20, 176, rng.randrange(65536)]), 0, *[rf() for _ in range(7)]),
    ]
    try:
        for i in range(2000):
            buf = bytearray(rng.choice(makers)().pack(enc))
            r = rng.random()
            if r < 0.3:
                buf[rng.randrange(len(buf))] = rng.randrange(256)
            elif r < 0.4:
                buf = buf[:rng.randrange(len(buf))]
            elif r < 0.5:
                buf = bytearray(rng.randbytes(rng.randrange(300)))
            sock.sendto(bytes(buf), rig.link.address("api"))
            if i % 50 == 49:
                rig.tick()
        c = rig.link.counters
        assert c["handler_error"] == 0 and c["api.rx_datagrams"] == 2000
        assert c["api.rx_bad_crc"] > 0 and c["api.rx_truncated"] > 0
        for cmd in rig.commands:
            vals = (cmd.vx, cmd.vy, cmd.vz, cmd.yaw_rate) + (() if cmd.yaw is None else (cmd.yaw,))
            assert all(math.isfinite(v) for v in vals)
            assert math.hypot(cmd.vx, cmd.vy, cmd.vz) <= 20.0 and abs(cmd.yaw_rate) <= 10.0
    finally:
        sock.close()
        rig.link.close()


def test_default_ports_follow_px4_sitl() -> None:
    c = VehicleLinkConfig()
    assert (c.api.local_port, c.api.remote_port) == (14580, 14540)
    assert (c.gcs.local_port, c.gcs.remote_port) == (18570, 14550)
    assert c.api.local_host == c.gcs.local_host == "127.0.0.1"
    c1 = VehicleLinkConfig.for_instance(1)
    assert c1.system_id == 2 and (c1.api.local_port, c1.api.remote_port) == (14581, 14541)
    assert OffboardClientConfig().listen_port == 14540
