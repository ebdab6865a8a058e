"""MAVLink 2 over a non-blocking UDP socket: encode, send, drain, decode, count.

Both ends of skyloop's MAVLink (the vehicle's links and the offboard client) use
:class:`UdpEndpoint`: one socket bound to a fixed local address (so the vehicle sends
*from* 14580/18570 as PX4 SITL does, and the client listens *on* 14540), a pymavlink
encoder with our system/component ids, and a decoder fed one datagram at a time.

Decoding rules (a frame never spans UDP datagrams, so nothing carries over):

* the decoder runs with pymavlink's ``robust_parsing``: garbage comes back as "bad data"
  instead of exceptions; every problem is counted in :attr:`UdpEndpoint.counters`
  (``rx_bad_prefix``, ``rx_bad_crc``, ``rx_bad_length``, ``rx_bad_signature``,
  ``rx_bad_data``, ``rx_unknown_msg_id``, ``rx_truncated`` for a partial frame left at
  the end of a datagram, ``rx_parse_error`` for anything pymavlink raises), never raised;
* a frame whose payload is longer than its message defines (pymavlink would cut it
  silently) is refused as ``rx_bad_length``; a shorter one is MAVLink 2's trailing-zero
  truncation and is accepted (zero-filled);
* security (:class:`~mavlink_bridge.security.LinkSecurity`): signature refusals are
  counted as ``rx_unsigned``, ``rx_bad_signature``, ``rx_replay``, ``rx_stale_timestamp``
  (accepted: ``rx_signed``, ``rx_unsigned_accepted``); refusals by sender as ``rx_own_id``
  and ``rx_sysid_not_allowed``. None of these is returned, and none moves the peer;
* good messages are returned with the sender's address; ``rx_msgs`` counts them. With
  ``follow_sender`` only *trusted* ones (signed when signing, from a listed system when
  there is an allow-list) make their sender the new peer.

The common dialect of ``pymavlink.dialects.v20`` is imported directly (MAVLink 2 framing
whatever ``MAVLINK20`` says); nothing here imports ``mavutil``. The parser/encoder is
:class:`~mavlink_bridge.security.SigningMAVLink` (pymavlink's, with our signature policy);
binding beyond loopback needs ``LinkSecurity(expose=True)``.
"""

from __future__ import annotations

import errno
import logging
import socket
from collections import Counter
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from mavlink_bridge.security import (
    SIGNATURE_REJECT_PREFIX,
    LinkSecurity,
    SignatureVerdict,
    SigningMAVLink,
    check_bind,
)

log = logging.getLogger(__name__)

Address = tuple[str, int]

_MAX_DATAGRAM = 65535


def _classify(reason: str) -> str:
    if reason.startswith(SIGNATURE_REJECT_PREFIX):
        return "rx_" + reason[len(SIGNATURE_REJECT_PREFIX):]
    r = reason.lower()
    for key, name in (("prefix", "rx_bad_prefix"), ("crc", "rx_bad_crc"),
                      ("length", "rx_bad_length"), ("signature", "rx_bad_signature")):
        if key in r:
            return name
    return "rx_bad_data"



class LinkBindError(ValueError):
    """A link's local UDP address cannot be bound (taken, or not an address here)."""

    def __init__(self, link: str, local: tuple[str, int], cause: OSError) -> None:
        super().__init__(f"MAVLink link {link!r} cannot listen on UDP {local[0]}:{local[1]}: "
                         f"{cause.strerror or cause}")
        self.link, self.local = link, local

class UdpEndpoint:
    """A bound, non-blocking UDP socket speaking MAVLink 2 as ``system_id/component_id``.

    ``remote`` is where unsolicited traffic goes until someone speaks to us; with
    ``follow_sender`` (PX4's behaviour) the latest trusted sender becomes the
    destination. ``security``: signing, allow-list, binding (default: none, loopback).
    """

    def __init__(self, local: Address, remote: Address | None, system_id: int,
                 component_id: int, name: str = "link", follow_sender: bool = True,
                 security: LinkSecurity | None = None) -> None:
        self.name = name
        self.follow_sender = follow_sender
        self.security = security or LinkSecurity()
        check_bind(local[0], self.security.expose, f"MAVLink link {name!r}")
        self.counters: Counter[str] = Counter()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.setblocking(False)
            self.sock.bind(local)
        except OSError as exc:
            self.sock.close()
            raise LinkBindError(name, local, exc) from None
        self.address: Address = self.sock.getsockname()[:2]
        self.remote = remote
        self.peer: Address | None = remote
        self.own_id = (system_id, component_id)
        self.mav = SigningMAVLink(system_id, component_id, self.security)
        self._closed = False

    # ------------------------------------------------------------------ send
    def send(self, msg: Any, addr: Address | None = None) -> bool:
        """Encode and send ``msg`` to ``addr`` (default: the current peer). False if there
        is nowhere to send or the OS refused (counted as ``tx_errors``)."""
        dest = addr or self.peer
        if dest is None or self._closed:
            return False
        if self.security.signing:
            self.mav.refresh_timestamp()
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        try:
            self.sock.sendto(buf, dest)
        except OSError as exc:  # e.g. ECONNREFUSED from an earlier ICMP, ENOBUFS
            self.counters["tx_errors"] += 1
            if self.counters["tx_errors"] & (self.counters["tx_errors"] - 1) == 0:
                log.warning("%s: send to %s failed: %s", self.name, dest, exc)
            return False
        self.counters["tx_msgs"] += 1
        return True

    # ------------------------------------------------------------------ receive
    def receive(self, max_datagrams: int = 1000) -> list[tuple[Any, Address]]:
        """Drain up to ``max_datagrams`` waiting datagrams; decoded messages with senders."""
        out: list[tuple[Any, Address]] = []
        for _ in range(max_datagrams):
            try:
                data, addr = self.sock.recvfrom(_MAX_DATAGRAM)
            except BlockingIOError:
                break
            except OSError as exc:
                if exc.errno in (errno.ECONNREFUSED, errno.ECONNRESET):
                    self.counters["rx_icmp_errors"] += 1
                    continue
                if self._closed:
                    break
                raise
            self.counters["rx_datagrams"] += 1
            msgs = self.decode(data)
            if self.follow_sender and any(self.security.trusted_sender(m) for m in msgs):
                self.peer = addr[:2]
            out.extend((m, addr[:2]) for m in msgs)
        return out

    def decode(self, data: bytes) -> list[Any]:
        """Decode one datagram; bad or refused parts are counted, good messages returned."""
        mav = self.mav
        # Fresh parser state per datagram (pymavlink keeps partial frames otherwise).
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink.HEADER_LEN_V1 + 2
        good: list[Any] = []
        try:
            msgs = mav.parse_buffer(data) or []
        except Exception as exc:  # robust parsing should not raise; never let it out
            self.counters["rx_parse_error"] += 1
            log.debug("%s: parse error %s", self.name, exc)
            msgs = []
        security = self.security
        for m in msgs:
            if isinstance(m, mavlink.MAVLink_bad_data):
                self.counters[_classify(str(getattr(m, "reason", "")))] += 1
            elif isinstance(m, mavlink.MAVLink_unknown):
                self.counters["rx_unknown_msg_id"] += 1
            elif m.get_header().mlen > type(m).unpacker.size:
                self.counters["rx_bad_length"] += 1
            elif (refusal := security.sender_refusal(m, self.own_id)) is not None:
                self.counters["rx_" + refusal] += 1
            else:
                if security.signing:
                    self.counters["rx_signed" if m.get_signed() else
                                  "rx_" + SignatureVerdict.UNSIGNED_ACCEPTED.value] += 1
                good.append(m)
        if mav.buf_len() > 0:
            self.counters["rx_truncated"] += 1
        self.counters["rx_msgs"] += len(good)
        return good

    def fileno(self) -> int:
        return self.sock.fileno()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.sock.close()
