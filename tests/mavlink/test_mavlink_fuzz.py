"""Fuzz: over 10,000 seeded random and mutated frames at a real VehicleLink over UDP.

The vehicle (a real Commander, armed and holding in the air, behind a VehicleLink on
127.0.0.1) gets one datagram at a time from :class:`mavlink_bridge.fuzz.FrameFuzzer`
and is polled after each. After every frame: poll did not raise, the commander's state,
arming, failsafe and setpoint, the delivered setpoints and the parameter table are as
before, and the counters moved exactly as the frame's ``expect`` says (where it says).
Afterwards a valid setpoint and a valid command are still handled (the parser recovers).
A second run does the same against a signed vehicle from an attacker without the key.
"""

from __future__ import annotations

import math
import socket
from collections import Counter
from collections.abc import Iterator

import pytest
from pymavlink.dialects.v20 import common as mavlink

from mavlink_bridge.fuzz import FrameFuzzer, FuzzConfig
from mavlink_bridge.interfaces import VelocityCommand
from mavlink_bridge.security import LinkSecurity, SigningMAVLink
from mavlink_bridge.vehicle_link import LinkConfig, VehicleLink, VehicleLinkConfig
from sitl.commander.machine import Commander, State

KEY = bytes(range(100, 132))
NOW = 5.0
N_FRAMES = 10_500
N_SIGNED = 3_000
IGNORED = ("api.rx_datagrams", "api.tx_msgs", "api.tx_errors")


class Vehicle:
    """A Commander holding in the air behind a VehicleLink whose API link talks to
    ``peer_port``."""

    def __init__(self, peer_port: int, security: LinkSecurity | None = None) -> None:
        self.commander = Commander()
        self.commander.reset(NOW, airborne=True)
        self.setpoints: list[VelocityCommand] = []
        cfg = VehicleLinkConfig(api=LinkConfig(0, peer_port), gcs=None, params_file=None,
                                security=security)
        self.link = VehicleLink(self.commander, cfg, on_setpoint=self._on_setpoint)

    def _on_setpoint(self, cmd: VelocityCommand, now: float, time_boot_ms: int = 0) -> None:
        self.setpoints.append(cmd)
        self.commander.setpoint(now, cmd.vx, cmd.vy, cmd.vz, cmd.yaw_rate,
                                body=cmd.frame_is_body, yaw=cmd.yaw)

    def snapshot(self) -> tuple:
        c = self.commander
        return (c.state, c.armed, c.failsafe, c.landed, c.crashed, c._sp, c._sp_body,
                c._sp_yaw, c._last_setpoint_time, len(self.setpoints),
                tuple(sorted(self.link.params.values.items())),
                self.link.endpoints["api"].peer)


def checked(counters: Counter[str]) -> Counter[str]:
    """The counters a frame's ``expect`` speaks for: rx refusals, setpoints, commands."""
    return Counter({k: v for k, v in counters.items() if v and k not in IGNORED and (
        k.startswith(("api.rx_", "setpoint.", "cmd.")) or k == "handler_error")})


def expected_delta(expect: dict[str, int]) -> Counter[str]:
    return Counter({(f"api.{k}" if k.startswith("rx_") else k): v for k, v in expect.items()})


def fuzz(vehicle: Vehicle, fuzzer: FrameFuzzer, sock: socket.socket, n: int,
         extra: Iterator[tuple[bytes, dict[str, int]]] | None = None) -> Counter[str]:
    """Send ``n`` frames one by one, checking after each; the kinds sent."""
    dest = vehicle.link.address("api")
    before, counts = vehicle.snapshot(), Counter()
    for i, frame in enumerate(fuzzer.frames(n)):
        c0 = checked(vehicle.link.counters)
        sock.sendto(frame.data, dest)
        vehicle.link.poll(NOW)
        c1 = checked(vehicle.link.counters)
        delta = c1 - c0
        assert vehicle.snapshot() == before, (i, frame)
        assert delta["setpoint.accepted"] == 0 and delta["handler_error"] == 0, (i, frame)
        assert not any(k.startswith("cmd.") and k.endswith(".0") for k in delta), (i, frame)
        if frame.expect is not None:
            assert delta == expected_delta(frame.expect), (i, frame, delta)
        counts[frame.kind] += 1
    return counts


@pytest.fixture
def sock() -> Iterator[socket.socket]:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.setblocking(False)
    yield s
    s.close()


def test_fuzz_10k_frames_no_crash_no_state_change_counted(sock: socket.socket) -> None:
    vehicle = Vehicle(sock.getsockname()[1])
    try:
        enc = mavlink.MAVLink(None, 245, 190)
        sock.sendto(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(enc),
                    vehicle.link.address("api"))
        vehicle.link.poll(NOW)
        start = vehicle.link.counters
        fuzzer = FrameFuzzer(FuzzConfig(seed=20261122,
                                        known_commands=frozenset(vehicle.link.commands),
                                        param_names=tuple(vehicle.link.params.values)))
        kinds = fuzz(vehicle, fuzzer, sock, N_FRAMES)
        c = vehicle.link.counters
        # Every kind was exercised, every datagram was read, nothing got through.
        assert sum(kinds.values()) == N_FRAMES >= 10_000 and len(kinds) >= 25
        assert c["api.rx_datagrams"] - start["api.rx_datagrams"] == N_FRAMES
        assert c["setpoint.accepted"] == 0 and c["handler_error"] == 0
        for key in ("api.rx_bad_crc", "api.rx_truncated", "api.rx_bad_length",
                    "api.rx_unknown_msg_id", "api.rx_bad_prefix", "api.rx_bad_data",
                    "api.rx_own_id", "setpoint.nan", "setpoint.inf", "setpoint.unknown_frame",
                    "setpoint.unsupported_type_mask", "setpoint.out_of_range",
                    "setpoint.wrong_target", "cmd.other_target", "cmd.unsupported",
                    "cmd.400.2", "cmd.176.2", "cmd.176.3", "cmd.22.2"):
            assert c[key] > 0, key
        # The parser recovers: a valid setpoint and a valid command are handled.
        sock.sendto(mavlink.MAVLink_set_position_target_local_ned_message(
            0, 1, 1, 1, 0x05C7, 0, 0, 0, 1.0, 0.5, 0, 0, 0, 0, 0, 0.25).pack(enc),
            vehicle.link.address("api"))
        sock.sendto(mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, 0, math.nan, math.nan, math.nan,
            math.nan).pack(enc), vehicle.link.address("api"))
        vehicle.link.poll(NOW)
        assert vehicle.setpoints == [VelocityCommand(0.5, 1.0, 0.0, -0.25, False, None)]
        assert vehicle.commander.state == State.LAND
        assert vehicle.link.counters["cmd.21.0"] == 1
    finally:
        vehicle.link.close()


def test_fuzz_signed_vehicle_from_an_attacker_without_the_key(sock: socket.socket) -> None:
    legit = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    legit.bind(("127.0.0.1", 0))
    vehicle = Vehicle(legit.getsockname()[1], LinkSecurity(secret_key=KEY))
    gcs = SigningMAVLink(245, 190, LinkSecurity(secret_key=KEY))
    dest = vehicle.link.address("api")
    try:
        hb = mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(gcs)
        legit.sendto(hb, dest)
        vehicle.link.poll(NOW)
        assert vehicle.link.endpoints["api"].peer == legit.getsockname()
        fuzzer = FrameFuzzer(FuzzConfig(seed=7, vehicle_signed=True,
                                        known_commands=frozenset(vehicle.link.commands),
                                        param_names=tuple(vehicle.link.params.values)))
        kinds = fuzz(vehicle, fuzzer, sock, N_SIGNED)
        sock.sendto(hb, dest)  # the attacker replays the genuine heartbeat
        vehicle.link.poll(NOW)
        c = vehicle.link.counters
        assert sum(kinds.values()) == N_SIGNED
        assert c["api.rx_unsigned"] > 0 and c["api.rx_bad_signature"] > 0
        assert c["api.rx_replay"] == 1 and c["api.rx_signed"] == 1
        assert vehicle.link.endpoints["api"].peer == legit.getsockname()  # not redirected
        # The genuine sender is not locked out by anything the attacker sent.
        legit.sendto(mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0).pack(gcs), dest)
        vehicle.link.poll(NOW)
        assert vehicle.commander.state == State.LAND and c["handler_error"] == 0
    finally:
        legit.close()
        vehicle.link.close()
