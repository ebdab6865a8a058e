"""A seeded generator of invalid MAVLink frames, each with the counters it must move.

Pure (no sockets, no clock): :class:`FrameFuzzer` yields :class:`FuzzFrame` datagrams
for the vehicle's fuzz test (``tests/mavlink/test_mavlink_fuzz.py``) and benchmark
(``benchmarks/bench_mavlink_fuzz.py``). Every frame is meant to be refused; ``expect``
says by which counters (:attr:`mavlink_bridge.vehicle_link.VehicleLink.counters` names,
``rx_*`` without the link prefix), or is None where the outcome is not predictable
(random garbage and random byte flips may hit any parser path).

Kinds (the frame itself is MAVLink 1 or 2 where it matters):

* framing: ``garbage`` (random bytes), ``bad_prefix`` (no start byte anywhere),
  ``bad_crc``, ``truncated``, ``length_field`` (header length larger than the data),
  ``over_length`` (valid CRC, payload longer than the message defines), ``unknown_id``,
  ``bad_incompat`` (unknown incompatibility flags), ``mutated`` (random byte flips);
* content, valid CRC: setpoints with NaN / inf / out-of-range values, unknown
  coordinate frames, unsupported type masks, wrong targets; COMMAND_LONG and
  COMMAND_INT with wrong targets, unknown command ids (not in ``known_commands``),
  arm/disarm param1 neither 0 nor 1, DO_SET_MODE with non-byte or unknown modes,
  takeoff to a non-finite, negative or too high altitude; HEARTBEAT with out-of-range
  enums; PARAM_SET with unknown names, wrong types, NaN and inf; frames claiming the
  vehicle's own ids (``own_id``).

With ``vehicle_signed`` the fuzzer plays an attacker without the key: every frame with
a valid CRC of a known message is unsigned (``rx_unsigned``) or signed with a wrong key
(``rx_bad_signature``), whatever its content.
"""

from __future__ import annotations

import math
import random
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from mavlink_bridge.security import LinkSecurity, SigningMAVLink
from mavlink_bridge.validate import SUPPORTED_MASKS, supported_mask

SPECIALS = (math.nan, math.inf, -math.inf, 0.0, -0.0, 1.0, -1.0, 1e38, -1e38, 3.4e38)
BAD_ALTITUDES = (math.inf, -math.inf, -1.0, 0.0, 101.0, 1e30, -1e-3)
WRONG_KEY = bytes(range(32))


@dataclass(frozen=True)
class FuzzFrame:
    """One datagram, what kind of bad it is, and the counter increments it must cause."""

    data: bytes
    kind: str
    expect: dict[str, int] | None


@dataclass(frozen=True)
class FuzzConfig:
    """Whom the frames target and what the vehicle is known to handle."""

    seed: int = 0
    system_id: int = 1  # the vehicle
    component_id: int = 1
    sender: tuple[int, int] = (245, 190)
    known_commands: frozenset[int] = frozenset()  # never sent as "unknown"
    param_names: tuple[str, ...] = ("MPC_XY_VEL_MAX",)
    vehicle_signed: bool = False  # the vehicle wants signatures; we have none


@dataclass
class FrameFuzzer:
    """Seeded source of invalid frames (see the module docstring)."""

    config: FuzzConfig = field(default_factory=FuzzConfig)

    def __post_init__(self) -> None:
        c = self.config
        self.rng = random.Random(c.seed)
        self.enc = mavlink.MAVLink(None, *c.sender)
        self.own = mavlink.MAVLink(None, c.system_id, c.component_id)
        self.forger = SigningMAVLink(*c.sender, LinkSecurity(secret_key=WRONG_KEY))
        self._other_sys = [s for s in range(256) if s != c.system_id]
        self._other_comp = [x for x in range(256) if x not in (0, c.component_id)]
        self._bad_frames = [f for f in range(256) if f not in (1, 8)]
        self._bad_mains = [m for m in range(256) if m not in (4, 6)]  # AUTO, OFFBOARD
        self._content: list[Callable[[], tuple[str, Any, dict[str, int]]]] = [
            self._setpoint, self._setpoint, self._setpoint, self._command, self._command,
            self._command, self._heartbeat, self._param_set]
        self._framing: list[tuple[float, Callable[[], FuzzFrame]]] = [
            (0.06, self._garbage), (0.04, self._bad_prefix), (0.08, self._bad_crc),
            (0.08, self._truncated), (0.04, self._length_field), (0.05, self._over_length),
            (0.05, self._unknown_id), (0.03, self._bad_incompat), (0.07, self._mutated)]

    def frames(self, n: int) -> Iterator[FuzzFrame]:
        for _ in range(n):
            yield self.frame()

    def frame(self) -> FuzzFrame:
        r = self.rng.random()
        for weight, make in self._framing:
            if r < weight:
                return make()
            r -= weight
        return self._content_frame()

    # ------------------------------------------------------------------ helpers
    def _f(self) -> float:
        rng = self.rng
        return rng.choice(SPECIALS) if rng.random() < 0.3 else rng.uniform(-30.0, 30.0)

    def _valid_frame(self) -> bytes:
        """A well-formed frame of some content message (v1 or v2, unsigned)."""
        _, msg, _ = self.rng.choice(self._content)()
        return msg.pack(self.enc, force_mavlink1=self.rng.random() < 0.2)

    def _encode(self, msg: Any, expect: dict[str, int]) -> tuple[bytes, dict[str, int]]:
        rng = self.rng
        c = self.config
        if c.vehicle_signed:
            if rng.random() < 0.5:
                return msg.pack(self.forger), {"rx_bad_signature": 1}
            return msg.pack(self.enc, force_mavlink1=rng.random() < 0.3), {"rx_unsigned": 1}
        v1 = rng.random() < 0.2
        if rng.random() < 0.03:
            return msg.pack(self.own, force_mavlink1=v1), {"rx_own_id": 1}
        return msg.pack(self.enc, force_mavlink1=v1), {"rx_msgs": 1, **expect}

    def _content_frame(self) -> FuzzFrame:
        kind, msg, expect = self.rng.choice(self._content)()
        data, expect = self._encode(msg, expect)
        return FuzzFrame(data, kind, expect)

    @staticmethod
    def _v2(msg_id: int, payload: bytes, sender: tuple[int, int], crc_extra: int,
            incompat: int = 0) -> bytes:
        header = struct.pack("<BBBBBBBHB", 0xFD, len(payload), incompat, 0, 0, *sender,
                             msg_id & 0xFFFF, msg_id >> 16)
        crc = mavlink.x25crc(header[1:] + payload)
        crc.accumulate(bytes([crc_extra]))
        return header + payload + struct.pack("<H", crc.crc)

    # ------------------------------------------------------------------ framing
    def _garbage(self) -> FuzzFrame:
        return FuzzFrame(self.rng.randbytes(self.rng.randrange(300)), "garbage", None)

    def _bad_prefix(self) -> FuzzFrame:
        data = bytes(b if b not in (0xFD, 0xFE) else b ^ 0x10
                     for b in self.rng.randbytes(self.rng.randrange(1, 120)))
        return FuzzFrame(data, "bad_prefix", {"rx_bad_prefix": 1})

    def _bad_crc(self) -> FuzzFrame:
        data = bytearray(self._valid_frame())
        data[-1 - self.rng.randrange(2)] ^= self.rng.randrange(1, 256)
        return FuzzFrame(bytes(data), "bad_crc", {"rx_bad_crc": 1})

    def _truncated(self) -> FuzzFrame:
        data = self._valid_frame()
        return FuzzFrame(data[:self.rng.randrange(1, len(data))], "truncated",
                         {"rx_truncated": 1})

    def _length_field(self) -> FuzzFrame:
        data = bytearray(self._valid_frame())
        header = 10 if data[0] == 0xFD else 6
        data[1] = self.rng.randrange(len(data) - header - 1, 256)  # more than is there
        return FuzzFrame(bytes(data), "length_field", {"rx_truncated": 1})

    def _over_length(self) -> FuzzFrame:
        rng = self.rng
        _, msg, _ = rng.choice(self._content)()
        kind = mavlink.mavlink_map[msg.get_msgId()]
        msg.pack(self.enc)
        payload = bytes(msg.get_payload()).ljust(kind.unpacker.size, b"\0")
        payload += rng.randbytes(rng.randrange(1, min(40, 256 - len(payload))))
        data = self._v2(msg.get_msgId(), payload, self.config.sender, kind.crc_extra)
        if self.config.vehicle_signed:
            return FuzzFrame(data, "over_length", {"rx_unsigned": 1})
        return FuzzFrame(data, "over_length", {"rx_bad_length": 1})

    def _unknown_id(self) -> FuzzFrame:
        rng = self.rng
        msg_id = rng.randrange(1 << 24)
        while msg_id in mavlink.mavlink_map:
            msg_id = rng.randrange(1 << 24)
        data = self._v2(msg_id, rng.randbytes(rng.randrange(1, 256)), self.config.sender,
                        rng.randrange(256))
        return FuzzFrame(data, "unknown_id", {"rx_unknown_msg_id": 1})

    def _bad_incompat(self) -> FuzzFrame:
        data = bytearray(self._valid_frame())
        if data[0] != 0xFD:
            return self._bad_crc()
        data[2] = self.rng.randrange(1, 128) << 1  # any flag but SIGNED (bit 0)
        return FuzzFrame(bytes(data), "bad_incompat", {"rx_bad_data": 1})

    def _mutated(self) -> FuzzFrame:
        data = bytearray(self._valid_frame())
        for _ in range(self.rng.randrange(1, 4)):
            data[self.rng.randrange(len(data))] ^= self.rng.randrange(1, 256)
        return FuzzFrame(bytes(data), "mutated", None)

    # ------------------------------------------------------------------ content
    def _setpoint(self) -> tuple[str, Any, dict[str, int]]:
        rng, c = self.rng, self.config
        target, comp = c.system_id, rng.choice((0, c.component_id))
        frame, mask = rng.choice((1, 8)), rng.choice(sorted(SUPPORTED_MASKS))
        v = [rng.uniform(-5.0, 5.0) for _ in range(3)]
        yaw, yaw_rate = rng.uniform(-3.0, 3.0), rng.uniform(-1.0, 1.0)
        kind = rng.choice(("wrong_target", "unknown_frame", "unsupported_type_mask", "nan",
                           "inf", "out_of_range"))
        if kind == "wrong_target":
            if rng.random() < 0.5:
                target = rng.choice(self._other_sys)
            else:
                comp = rng.choice(self._other_comp)
        elif kind == "unknown_frame":
            frame = rng.choice(self._bad_frames)
        elif kind == "unsupported_type_mask":
            mask = rng.randrange(1 << 16)
            while supported_mask(mask) is not None:
                mask = rng.randrange(1 << 16)
        elif kind in ("nan", "inf"):
            bad = math.nan if kind == "nan" else rng.choice((math.inf, -math.inf))
            slots = ["v0", "v1", "v2"] + (["yaw_rate"] if mask == 0x05C7 else []) + (
                ["yaw"] if mask == 0x09C7 else [])
            slot = rng.choice(slots)
            if slot.startswith("v"):
                v[int(slot[1])] = bad
            elif slot == "yaw":
                yaw = bad
            else:
                yaw_rate = bad
        elif rng.random() < 0.6 or mask == 0x0DC7:
            v[rng.randrange(3)] = rng.choice((1.0, -1.0)) * rng.uniform(20.5, 1e6)
        elif mask == 0x05C7:
            yaw_rate = rng.choice((1.0, -1.0)) * rng.uniform(10.5, 1e6)
        else:
            yaw = rng.choice((1.0, -1.0)) * rng.uniform(6.3, 1e6)
        msg = mavlink.MAVLink_set_position_target_local_ned_message(
            rng.randrange(1 << 32), target, comp, frame, mask, self._f(), self._f(), self._f(),
            *v, self._f(), self._f(), self._f(), yaw, yaw_rate)
        return f"setpoint_{kind}", msg, {f"setpoint.{kind}": 1}

    def _command(self) -> tuple[str, Any, dict[str, int]]:
        rng, c = self.rng, self.config
        target, comp = c.system_id, rng.choice((0, c.component_id))
        p = [self._f() for _ in range(7)]
        kind = rng.choice(("other_target", "unsupported", "arm_param", "set_mode_bytes",
                           "set_mode_unknown", "takeoff_altitude"))
        if kind == "other_target":
            command = rng.randrange(1 << 16)
            if rng.random() < 0.5:
                target = rng.choice(self._other_sys)
            else:
                comp = rng.choice(self._other_comp)
            expect = {"cmd.other_target": 1}
        elif kind == "unsupported":
            command = rng.randrange(1 << 16)
            while command in c.known_commands:
                command = rng.randrange(1 << 16)
            expect = {"cmd.unsupported": 1}
        elif kind == "arm_param":
            command = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
            p[0] = rng.choice((math.nan, math.inf, -math.inf, 0.5, 2.0, -1.0, 1e9))
            expect = {"cmd.400.2": 1}
        elif kind == "set_mode_bytes":
            command = mavlink.MAV_CMD_DO_SET_MODE
            p[:3] = [1.0, 6.0, 0.0]
            p[rng.randrange(3)] = rng.choice((math.nan, math.inf, -1.0, 256.0, 2.5, 1e9))
            expect = {"cmd.176.2": 1}
        elif kind == "set_mode_unknown":
            command = mavlink.MAV_CMD_DO_SET_MODE
            main = rng.choice(self._bad_mains)
            base = rng.choice((1.0, 0.0, 128.0)) if rng.random() < 0.2 else 1.0
            p[:3] = [base, float(main), float(rng.randrange(256))]
            expect = {"cmd.176.3": 1}
        else:
            command = mavlink.MAV_CMD_NAV_TAKEOFF
            p[6] = rng.choice(BAD_ALTITUDES)
            expect = {"cmd.22.2": 1}
        if rng.random() < 0.5:
            msg = mavlink.MAVLink_command_long_message(target, comp, command, 0, *p)
        else:
            msg = mavlink.MAVLink_command_int_message(
                target, comp, rng.randrange(256), command, 0, 0, *p[:4],
                rng.randrange(-2**31, 2**31), rng.randrange(-2**31, 2**31), p[6])
        return f"command_{kind}", msg, expect

    def _heartbeat(self) -> tuple[str, Any, dict[str, int]]:
        rng = self.rng
        msg = mavlink.MAVLink_heartbeat_message(rng.randrange(256), rng.randrange(256),
                                                rng.randrange(256), rng.randrange(1 << 32),
                                                rng.randrange(256), rng.randrange(256))
        return "heartbeat_enums", msg, {}

    def _param_set(self) -> tuple[str, Any, dict[str, int]]:
        rng, c = self.rng, self.config
        r = rng.random()
        if r < 0.3:
            name = bytes(rng.choice(b"ABCDEFGHIJKLMNOPQRSTUVWXYZ_") for _ in range(12))
            kind, ptype, value = "param_unknown", 9, self._f()
        elif r < 0.6:
            name = rng.choice(c.param_names).encode()
            kind, ptype, value = "param_type", rng.choice((0, 11, 200, 255)), self._f()
        else:
            name = rng.choice(c.param_names).encode()
            kind, ptype, value = "param_nonfinite", 9, rng.choice(
                (math.nan, math.inf, -math.inf))
        msg = mavlink.MAVLink_param_set_message(c.system_id, c.component_id, name, value,
                                                ptype)
        return kind, msg, {}
