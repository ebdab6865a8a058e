"""MAVLink FTP, answered as "not supported" so ground stations fall back at once.

The vehicle has no file system to offer. Without an answer, a ground station that tries
MAVLink FTP first waits for its timeouts: MAVProxy asks for ``@PARAM/param.pck`` and
falls back to PARAM_REQUEST_LIST after ~11 s. So every FILE_TRANSFER_PROTOCOL request
addressed to the vehicle is answered right away, to its sender, as PX4's server frames a
reply (``payload``: seq u16, session u8, opcode u8, size u8, req_opcode u8,
burst_complete u8, padding u8, offset u32, data):

* TerminateSession (1) and ResetSessions (2): ACK (opcode 128), size 0 -- there is never
  an open session, so closing one succeeds;
* every other opcode: NAK (opcode 129), size 1, data ``[ERR_UNKNOWN_COMMAND]`` (7).

The reply's ``seq`` is the request's plus one and its ``session`` and ``req_opcode``
echo the request, as clients match replies by them. Requests for other systems or
components, and replies (opcode >= 128), are counted and not answered.
Counters: ``ftp.nak``, ``ftp.ack``, ``ftp.other_target``, ``ftp.not_a_request``.
"""

from __future__ import annotations

import struct
from collections import Counter
from typing import Any

from mavlink_bridge.transport import mavlink

OP_TERMINATE_SESSION = 1
OP_RESET_SESSIONS = 2
OP_ACK = 128
OP_NAK = 129
ERR_UNKNOWN_COMMAND = 7
_HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst, pad, ofs
PAYLOAD_LEN = 251


def reply_payload(request: bytes | list[int]) -> bytes | None:
    """The reply payload for a request payload (None if it is not a request)."""
    head = bytes(bytearray(request[:_HEADER.size])).ljust(_HEADER.size, b"\x00")
    seq, session, opcode = _HEADER.unpack(head)[:3]
    if opcode >= OP_ACK:
        return None
    if opcode in (OP_TERMINATE_SESSION, OP_RESET_SESSIONS):
        out = _HEADER.pack((seq + 1) & 0xFFFF, session, OP_ACK, 0, opcode, 0, 0, 0)
    else:
        out = _HEADER.pack((seq + 1) & 0xFFFF, session, OP_NAK, 1, opcode, 0, 0, 0) + \
            bytes([ERR_UNKNOWN_COMMAND])
    return out.ljust(PAYLOAD_LEN, b"\x00")


class FtpRefuser:
    """Answers FILE_TRANSFER_PROTOCOL requests for ``system_id``/``component_id``."""

    def __init__(self, system_id: int, component_id: int) -> None:
        self.system_id = system_id
        self.component_id = component_id
        self.counters: Counter[str] = Counter()

    def reply(self, msg: Any) -> Any | None:
        """The FILE_TRANSFER_PROTOCOL to send back to ``msg``'s sender, or None."""
        if msg.target_system not in (0, self.system_id) or \
                msg.target_component not in (0, self.component_id):
            self.counters["other_target"] += 1
            return None
        payload = reply_payload(msg.payload)
        if payload is None:
            self.counters["not_a_request"] += 1
            return None
        self.counters["ack" if payload[3] == OP_ACK else "nak"] += 1
        return mavlink.MAVLink_file_transfer_protocol_message(
            msg.target_network, msg.get_srcSystem(), msg.get_srcComponent(), payload)
