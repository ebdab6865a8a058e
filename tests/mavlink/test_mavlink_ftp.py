"""MAVLink FTP requests are refused at once (NAK), so ground stations fall back fast.

A pymavlink ground station on real UDP (127.0.0.1) against a VehicleLink with a real
Commander (tests/gcs_rig.py). The request is the one MAVProxy sends first to fetch
parameters (OpenFileRO ``@PARAM/param.pck``).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path

import pytest
from gcs_rig import GcsRig, of_type
from pymavlink.dialects.v20 import common as mavlink

HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst, pad, ofs
OPEN_FILE_RO, TERMINATE_SESSION, ACK, NAK, ERR_UNKNOWN_COMMAND = 4, 1, 128, 129, 7


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[GcsRig]:
    r = GcsRig(tmp_path / "params.json")
    yield r
    r.close()


def ftp(opcode: int, seq: int = 41, session: int = 7, data: bytes = b"",
        target: tuple[int, int] = (1, 1)) -> object:
    payload = HEADER.pack(seq, session, opcode, len(data), 0, 0, 0, 0) + data
    return mavlink.MAVLink_file_transfer_protocol_message(0, *target,
                                                          payload.ljust(251, b"\x00"))


def replies(rig: GcsRig, msg: object) -> list[tuple[int, ...]]:
    got = of_type(rig.exchange(msg), "FILE_TRANSFER_PROTOCOL")
    assert all((m.target_system, m.target_component) == (255, 190) for m in got)
    return [HEADER.unpack(bytes(m.payload[:HEADER.size])) + (m.payload[HEADER.size],)
            for m in got]


def test_open_file_is_refused_with_a_nak_echoing_the_request(rig: GcsRig) -> None:
    path = b"@PARAM/param.pck?withdefaults=1"
    [(seq, session, opcode, size, req_opcode, _, _, _, err)] = replies(
        rig, ftp(OPEN_FILE_RO, seq=41, session=7, data=path))
    assert (seq, session, opcode, size, req_opcode, err) == (42, 7, NAK, 1, OPEN_FILE_RO,
                                                            ERR_UNKNOWN_COMMAND)
    assert rig.link.counters["ftp.nak"] == 1
    # seq wraps at 16 bits; any other opcode is refused the same way
    [reply] = replies(rig, ftp(3, seq=0xFFFF, session=2, data=b"/"))  # ListDirectory
    assert reply[:5] == (0, 2, NAK, 1, 3)


def test_terminate_session_is_acked_replies_and_other_targets_are_not_answered(
        rig: GcsRig) -> None:
    [reply] = replies(rig, ftp(TERMINATE_SESSION, seq=9, session=3))
    assert reply[:5] == (10, 3, ACK, 0, TERMINATE_SESSION)
    assert replies(rig, ftp(OPEN_FILE_RO, target=(2, 1))) == []
    assert replies(rig, ftp(OPEN_FILE_RO, target=(1, 5))) == []
    assert replies(rig, ftp(NAK)) == []  # a reply, not a request
    c = rig.link.counters
    assert (c["ftp.ack"], c["ftp.nak"], c["ftp.other_target"], c["ftp.not_a_request"]) == \
        (1, 0, 2, 1)
