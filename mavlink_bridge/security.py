"""MAVLink link security: MAVLink 2 signing, a sender allow-list, loopback-only binding.

What it implements (issue 5, section 5), for both ends of skyloop's MAVLink (the vehicle's
links and the offboard client), through :class:`LinkSecurity` handed to
:class:`mavlink_bridge.transport.UdpEndpoint`:

* **Signing** (MAVLink 2 message signing, pymavlink's implementation): with a 32-byte
  ``secret_key`` every outgoing frame is signed (heartbeats and telemetry included) and
  every incoming frame must carry a valid signature, except the message ids in
  ``unsigned_ok``. Default: only RADIO_STATUS (109) is accepted unsigned, as PX4 and
  ArduPilot do (a radio modem injects it and cannot sign). An unsigned HEARTBEAT is
  *refused*: on a link that follows whoever spoke last, accepting it would let anyone
  redirect the vehicle's telemetry. An unsigned RADIO_STATUS is delivered but does not
  move the link's peer either (only authenticated traffic does, see the transport).
  Refusals are counted by reason (:class:`SignatureVerdict`): ``unsigned``,
  ``bad_signature``, ``replay`` (timestamp not newer than the last one accepted from
  that link/system/component), ``stale_timestamp`` (a new stream more than 60 s behind
  our clock, pymavlink's rule). :class:`SigningMAVLink` is pymavlink's parser with one
  change: the signature is checked *before* the replay table is updated, and with a
  constant-time compare. pymavlink records a frame's timestamp before it knows whether
  the signature is good, so one forged frame with a far-future timestamp would make
  every genuine frame after it look like a replay (found by the fuzz test).
* **Allow-list** (``allow_sysids``): when given, state-changing messages
  (:data:`STATE_CHANGING`: commands, setpoints, parameter and mission writes) from any
  other system id are refused (``sysid_not_allowed``). System id 0 is the broadcast
  address, never a sender: it cannot be listed. The vehicle's own system id may be
  listed (a companion computer on the vehicle shares it); a frame claiming the
  vehicle's own system *and* component id is always refused (``own_id``): it is an
  echo or a spoof.
* **Binding**: loopback unless ``expose`` is set; :func:`check_bind` refuses any other
  local address with a clear error. :func:`bind_host` gives the address to bind.

Command-line glue for the nodes: :func:`security_from_args` turns their flags
(``--signing-key-file``, ``--allow-sysid N`` repeatable, ``--expose``:
``skyloop.cli.stack_settings.SecurityFlags``; the key may also come from the environment
variable ``SKYLOOP_MAVLINK_KEY``) into a :class:`LinkSecurity`. A key
is 64 hex digits (the 32 bytes) or a passphrase, hashed with SHA-256 as MAVProxy's
``signing setup`` does, so the same passphrase works in MAVProxy.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import os
import struct
import time
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

KEY_ENV = "SKYLOOP_MAVLINK_KEY"
SIGNING_EPOCH = 1420070400  # 2015-01-01 UTC; signing timestamps count 10 us from here
NEW_STREAM_MAX_LAG = 6_000_000  # 60 s in 10 us units (pymavlink's rule for new streams)

#: Messages that change the vehicle's state: refused from senders off the allow-list.
STATE_CHANGING = frozenset({
    "COMMAND_LONG", "COMMAND_INT", "COMMAND_CANCEL", "SET_MODE",
    "SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT", "SET_ATTITUDE_TARGET",
    "MANUAL_CONTROL", "RC_CHANNELS_OVERRIDE", "SET_HOME_POSITION", "SET_GPS_GLOBAL_ORIGIN",
    "PARAM_SET", "PARAM_EXT_SET", "MISSION_COUNT", "MISSION_ITEM", "MISSION_ITEM_INT",
    "MISSION_CLEAR_ALL", "MISSION_SET_CURRENT", "MISSION_WRITE_PARTIAL_LIST",
    "SETUP_SIGNING", "FILE_TRANSFER_PROTOCOL", "LOG_ERASE",
})


class SignatureVerdict(StrEnum):
    """What the signature check said about the last frame (counter ``rx_<value>``)."""

    SIGNED = "signed"  # good signature, fresh timestamp
    UNSIGNED_ACCEPTED = "unsigned_accepted"  # unsigned, of a type in ``unsigned_ok``
    UNSIGNED = "unsigned"  # refused: no signature
    BAD_SIGNATURE = "bad_signature"  # refused: signature does not match the key
    REPLAY = "replay"  # refused: timestamp not newer than the stream's last
    STALE_TIMESTAMP = "stale_timestamp"  # refused: new stream over 60 s behind


REFUSED = frozenset({SignatureVerdict.UNSIGNED, SignatureVerdict.BAD_SIGNATURE,
                     SignatureVerdict.REPLAY, SignatureVerdict.STALE_TIMESTAMP})
SIGNATURE_REJECT_PREFIX = "signature rejected: "


@dataclass(frozen=True)
class LinkSecurity:
    """Security settings of one MAVLink endpoint (see the module docstring).

    ``secret_key``: 32 bytes, or None for no signing. ``link_id``: the signing link id
    we send with. ``initial_timestamp``: signing timestamp to start from (10 us units
    since 2015), then +1 per frame sent; None: follow the wall clock (read at each send,
    so a long-running vehicle's stream never falls a minute behind the clock of a ground
    station connecting later, which would refuse it as stale).
    ``allow_sysids``: system ids allowed to send state-changing messages (None: any).
    ``expose``: allow binding to a non-loopback address.
    """

    secret_key: bytes | None = None
    link_id: int = 0
    initial_timestamp: int | None = None
    unsigned_ok: frozenset[int] = frozenset({mavlink.MAVLINK_MSG_ID_RADIO_STATUS})
    allow_sysids: frozenset[int] | None = None
    expose: bool = False

    def __post_init__(self) -> None:
        if self.secret_key is not None and len(self.secret_key) != 32:
            raise ValueError(f"MAVLink signing key must be 32 bytes, got {len(self.secret_key)}")
        if not 0 <= self.link_id <= 255:
            raise ValueError(f"signing link id must be 0..255, got {self.link_id}")
        if self.allow_sysids is not None:
            object.__setattr__(self, "allow_sysids", frozenset(self.allow_sysids))
            bad = sorted(s for s in self.allow_sysids if not 1 <= s <= 255)
            if bad:
                raise ValueError(f"--allow-sysid must be 1..255 (0 is broadcast, not a "
                                 f"sender), got {bad}")

    @property
    def signing(self) -> bool:
        return self.secret_key is not None

    def sender_refusal(self, msg: Any, own: tuple[int, int]) -> str | None:
        """Why a decoded message is refused by sender (``own_id``, ``sysid_not_allowed``),
        or None if admitted."""
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if src == own:
            return "own_id"
        if self.allow_sysids is not None and src[0] not in self.allow_sysids and \
                msg.get_type() in STATE_CHANGING:
            return "sysid_not_allowed"
        return None

    def trusted_sender(self, msg: Any) -> bool:
        """May this (admitted) message move the link's peer? Only signed traffic when
        signing, only listed systems when there is a list."""
        if self.signing and not msg.get_signed():
            return False
        return self.allow_sysids is None or msg.get_srcSystem() in self.allow_sysids


def signing_timestamp_now() -> int:
    """The current MAVLink signing timestamp (10 us units since 2015-01-01 UTC)."""
    return int(max(time.time() - SIGNING_EPOCH, 0.0) * 100_000)


class SigningMAVLink(mavlink.MAVLink):
    """pymavlink's MAVLink (framing, CRC, signing) with our signature policy.

    :attr:`verdict` tells what the signature check said about the last decoded frame
    (None when no key is set or the frame never reached the check); a refused frame
    raises ``MAVError("signature rejected: <verdict>")``, which robust parsing turns
    into bad data that the transport counts under ``rx_<verdict>``.
    """

    def __init__(self, system_id: int, component_id: int,
                 security: LinkSecurity | None = None) -> None:
        super().__init__(None, srcSystem=system_id, srcComponent=component_id)
        self.robust_parsing = True
        self.verdict: SignatureVerdict | None = None
        self.security = sec = security or LinkSecurity()
        if sec.secret_key is not None:
            self.signing.secret_key = sec.secret_key
            self.signing.sign_outgoing = True
            self.signing.link_id = sec.link_id
            self.signing.timestamp = sec.initial_timestamp if sec.initial_timestamp \
                is not None else signing_timestamp_now()
            self.signing.allow_unsigned_callback = self._allow_unsigned

    def refresh_timestamp(self) -> None:
        """Before signing a frame: catch the timestamp up with the wall clock (unless
        ``initial_timestamp`` pinned it)."""
        if self.security.initial_timestamp is None and self.signing.sign_outgoing:
            self.signing.timestamp = max(self.signing.timestamp, signing_timestamp_now())

    def decode(self, msgbuf: bytearray) -> Any:
        self.verdict = None
        try:
            return super().decode(msgbuf)
        except mavlink.MAVError as exc:
            if self.verdict in REFUSED:
                raise mavlink.MAVError(f"{SIGNATURE_REJECT_PREFIX}{self.verdict.value}") \
                    from exc
            raise

    def check_signature(self, msgbuf: bytearray, srcSystem: int, srcComponent: int) -> bool:
        """Signature first (constant time), then the replay rules; only a frame with a
        good signature updates the stream's timestamp and our clock."""
        signing = self.signing
        assert signing.secret_key is not None
        digest = hashlib.sha256(signing.secret_key + bytes(msgbuf[:-6])).digest()[:6]
        if not hmac.compare_digest(digest, bytes(msgbuf[-6:])):
            self.verdict = SignatureVerdict.BAD_SIGNATURE
            return False
        tlow, thigh = struct.unpack("<IH", bytes(msgbuf[-12:-6]))
        timestamp = tlow + (thigh << 32)
        stream = (msgbuf[-13], srcSystem, srcComponent)
        last = signing.stream_timestamps.get(stream)
        if last is not None and timestamp <= last:
            self.verdict = SignatureVerdict.REPLAY
            return False
        if last is None and timestamp + NEW_STREAM_MAX_LAG < signing.timestamp:
            self.verdict = SignatureVerdict.STALE_TIMESTAMP
            return False
        signing.stream_timestamps[stream] = timestamp
        signing.timestamp = max(signing.timestamp, timestamp)
        self.verdict = SignatureVerdict.SIGNED
        return True

    def _allow_unsigned(self, mav: Any, msg_id: int) -> bool:
        if self.verdict in REFUSED:  # signed, but badly: never a second chance
            return False
        ok = msg_id in self.security.unsigned_ok
        self.verdict = SignatureVerdict.UNSIGNED_ACCEPTED if ok else SignatureVerdict.UNSIGNED
        return ok


# ------------------------------------------------------------------ binding
def is_loopback(host: str) -> bool:
    """True for ``localhost`` and 127.0.0.0/8 / ::1 addresses."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_bind(host: str, expose: bool, what: str = "MAVLink link") -> None:
    """Refuse to bind a non-loopback address unless ``expose`` was asked for."""
    if not expose and not is_loopback(host):
        raise ValueError(f"refusing to bind {what} to {host or '0.0.0.0'!r}: that exposes "
                         f"the vehicle beyond this machine; pass --expose to allow it")


def bind_host(expose: bool) -> str:
    """The local address to bind: all interfaces with ``expose``, else loopback."""
    return "0.0.0.0" if expose else "127.0.0.1"


# ------------------------------------------------------------------ keys and CLI
def key_from_text(text: str) -> bytes:
    """64 hex digits -> those 32 bytes; anything else -> SHA-256 of it (MAVProxy's
    passphrase rule)."""
    text = text.strip()
    if not text:
        raise ValueError("empty MAVLink signing key")
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    return hashlib.sha256(text.encode("utf-8")).digest()


def load_key(path: Path | None, env: Mapping[str, str] | None = None) -> bytes | None:
    """The signing key from ``path`` (text, or 32 raw bytes), else from the environment
    variable ``SKYLOOP_MAVLINK_KEY``, else None."""
    if path is not None:
        raw = Path(path).read_bytes()
        try:
            return key_from_text(raw.decode("utf-8"))
        except UnicodeDecodeError:
            if len(raw) == 32:
                return raw
            raise ValueError(f"{path}: not a text key and not 32 raw bytes") from None
    value = (os.environ if env is None else env).get(KEY_ENV)
    return key_from_text(value) if value else None


def security_from_args(args: Any, env: Mapping[str, str] | None = None) -> LinkSecurity:
    """The :class:`LinkSecurity` a node's security flags ask for (``signing_key_file``,
    ``allow_sysid``, ``expose``: ``skyloop.cli.stack_settings.SecurityFlags``; missing
    ones are off)."""
    allow = getattr(args, "allow_sysid", None)
    return LinkSecurity(secret_key=load_key(getattr(args, "signing_key_file", None), env),
                        allow_sysids=None if not allow else frozenset(allow),
                        expose=bool(getattr(args, "expose", False)))
