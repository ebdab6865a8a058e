"""MAVLink bad-input benchmark: the fuzz test's frames, 1,000,000 of them (quick: 20,000).

The frames come from :class:`mavlink_bridge.fuzz.FrameFuzzer` (seeded; generated once,
outside the timing): garbage, bad CRC, truncated, wrong lengths, unknown ids, MAVLink 1
and 2, NaN/inf/out-of-range setpoints and commands, wrong targets. Keys (median of
several repeats, one core):

- ``mavlink_fuzz_udp_frames_per_s``: the whole path: sent over UDP on 127.0.0.1 in
  batches of 64 to a VehicleLink (real Commander, armed and holding) and polled, so the
  parser, the validators and the command handlers all run; the sender shares the core.
- ``mavlink_fuzz_parser_frames_per_s``: the parser alone, in process (each frame fed to
  the API endpoint's ``decode``: framing, CRC, length and sender checks, counters).
- ``mavlink_fuzz_parser_signed_frames_per_s``: the same at a vehicle with a signing key
  (an attacker's frames: unsigned or wrongly signed, every signature checked).
- ``mavlink_fuzz_crashes`` (exceptions out of ``poll``/``decode``; must be 0),
  ``mavlink_fuzz_lost`` (datagrams sent but not read), ``mavlink_fuzz_accepted``
  (setpoints and commands accepted from the fuzz frames; must be 0) and
  ``mavlink_fuzz_counters`` (the vehicle's counters after one UDP run).

Run alone: ``skyloop bench --only mavlink_fuzz [--quick] [--json PATH]``.
"""

from __future__ import annotations

import logging
import socket
import statistics
import time
from collections import Counter

from mavlink_bridge.fuzz import FrameFuzzer, FuzzConfig
from mavlink_bridge.security import LinkSecurity
from mavlink_bridge.transport import UdpEndpoint
from mavlink_bridge.vehicle_link import LinkConfig, VehicleLink, VehicleLinkConfig
from sitl.commander.machine import Commander

NOW = 5.0
BATCH = 64  # datagrams in flight before a poll (well inside the socket buffer)
KEY = bytes(range(32, 64))


def make_frames(n: int, **config) -> list[bytes]:
    """``n`` fuzz frames; command ids and parameter names are the vehicle's own."""
    with VehicleLink(Commander(), VehicleLinkConfig(api=LinkConfig(0, 9), gcs=None,
                                                    params_file=None)) as link:
        known, names = frozenset(link.commands), tuple(link.params.values)
    fuzzer = FrameFuzzer(FuzzConfig(seed=20261122, known_commands=known, param_names=names,
                                    **config))
    return [f.data for f in fuzzer.frames(n)]


def parser_rate(frames: list[bytes], security: LinkSecurity | None = None) -> tuple[float, int]:
    """(frames/s, crashes) feeding every frame to one endpoint's decoder."""
    ep = UdpEndpoint(("127.0.0.1", 0), None, 1, 1, security=security)
    crashes = 0
    try:
        t0 = time.perf_counter()
        for data in frames:
            try:
                ep.decode(data)
            except Exception:  # counted: the benchmark reports it, the goal is 0
                crashes += 1
        return len(frames) / (time.perf_counter() - t0), crashes
    finally:
        ep.close()


def udp_rate(frames: list[bytes]) -> tuple[float, int, Counter[str]]:
    """(frames/s, crashes, counters) through a VehicleLink over loopback UDP."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    commander = Commander()
    commander.reset(NOW, airborne=True)
    link = VehicleLink(commander, VehicleLinkConfig(
        api=LinkConfig(0, sock.getsockname()[1]), gcs=None, params_file=None))
    dest, crashes = link.address("api"), 0
    try:
        t0 = time.perf_counter()
        for i in range(0, len(frames), BATCH):
            for data in frames[i:i + BATCH]:
                sock.sendto(data, dest)
            try:
                link.poll(NOW)
            except Exception:  # counted, never expected
                crashes += 1
            try:  # the vehicle's ACKs: read and dropped
                while True:
                    sock.recv(65535)
            except BlockingIOError:
                pass
        rate = len(frames) / (time.perf_counter() - t0)
        counters = link.counters
        counters["commander_state_changed"] = int(commander.state != "HOLD")
        return rate, crashes, counters
    finally:
        link.close()
        sock.close()


def run(quick: bool) -> dict:
    n, repeats = (20_000, 5) if quick else (1_000_000, 3)
    logging.getLogger("mavlink_bridge").setLevel(logging.ERROR)  # rate-limited anyway
    frames = make_frames(n)
    signed = make_frames(min(n, 100_000), vehicle_signed=True)
    udp, parser, parser_signed = [], [], []
    crashes = 0
    counters: Counter[str] = Counter()
    for _ in range(repeats):
        rate, bad, counters = udp_rate(frames)
        udp.append(rate)
        crashes += bad
        rate, bad = parser_rate(frames)
        parser.append(rate)
        crashes += bad
        rate, bad = parser_rate(signed, LinkSecurity(secret_key=KEY))
        parser_signed.append(rate)
        crashes += bad
    accepted = counters["setpoint.accepted"] + sum(
        v for k, v in counters.items() if k.startswith("cmd.") and k.endswith(".0"))
    return {
        "mavlink_fuzz_frames": n,
        "mavlink_fuzz_udp_frames_per_s": statistics.median(udp),
        "mavlink_fuzz_parser_frames_per_s": statistics.median(parser),
        "mavlink_fuzz_parser_signed_frames_per_s": statistics.median(parser_signed),
        "mavlink_fuzz_crashes": crashes,
        "mavlink_fuzz_lost": n - counters["api.rx_datagrams"],
        "mavlink_fuzz_accepted": accepted + counters["commander_state_changed"],
        "mavlink_fuzz_counters": {k: v for k, v in sorted(counters.items())
                                  if v and not k.startswith(("api.tx", "commander_"))},
    }
