"""The MAVLink parameter protocol over skyloop's parameter table (:mod:`bus.params`).

Implements, as PX4 answers them:

* PARAM_REQUEST_LIST -> every PARAM_VALUE, ``param_index`` 0..n-1 in table order and
  ``param_count`` n in each;
* PARAM_REQUEST_READ by name (``param_index`` -1) or by index -> that PARAM_VALUE; an
  unknown name or index -> a STATUSTEXT, counted (``read_unknown``), no PARAM_VALUE;
* PARAM_SET -> validated with :func:`bus.params.check` (name, finite, range, integer);
  accepted: the new PARAM_VALUE to every link, persisted, ``on_change(name, value)``;
  refused (out of range, not a number, wrong ``param_type``): PARAM_VALUE with the
  *current* value to the sender (so the ground station shows it was not taken), plus a
  STATUSTEXT and a counter; unknown name: a STATUSTEXT and a counter.

Types: ``kind`` "float" is MAV_PARAM_TYPE_REAL32 (value in the float field), "int" is
MAV_PARAM_TYPE_INT32 encoded bytewise in the float field (PX4's
MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE). ``param_id`` is 16 bytes, NUL-padded,
not NUL-terminated when a name has 16 characters.

Persistence: one JSON file per vehicle, ``{"format": "skyloop-params/1", "params":
{name: value}}``, written atomically (a temporary file in the same directory, fsync,
``os.replace``) after every accepted change. The default path is
:func:`default_params_file`: ``$XDG_STATE_HOME/skyloop/params-sys<system id>.json``
(``~/.local/state/...`` without XDG_STATE_HOME); None keeps parameters in memory only.
A missing file means defaults; an unreadable/corrupt file is logged as an error, counted
(``load_error``) and defaults are used; unknown names or invalid values in it are
skipped one by one (``load_skipped``), the rest kept.
"""

from __future__ import annotations

import json
import logging
import os
import struct
import tempfile
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from bus import params as table
from mavlink_bridge.transport import mavlink

log = logging.getLogger(__name__)

FILE_FORMAT = "skyloop-params/1"
PARAM_TYPE = {"float": mavlink.MAV_PARAM_TYPE_REAL32, "int": mavlink.MAV_PARAM_TYPE_INT32}


class LinkOps(Protocol):
    """What a protocol service needs from the vehicle's links."""

    def broadcast(self, msg: Any) -> None: ...

    def statustext(self, text: str, severity: str | int = "info") -> None: ...


def default_params_file(system_id: int) -> Path:
    """``$XDG_STATE_HOME/skyloop/params-sys<id>.json`` (XDG default ``~/.local/state``)."""
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"),
                                                            ".local", "state")
    return Path(base) / "skyloop" / f"params-sys{system_id}.json"


def encode_value(kind: str, value: float) -> float:
    """The PARAM_VALUE.param_value float for a table value (INT32: bytewise)."""
    if kind == "int":
        return struct.unpack("<f", struct.pack("<i", int(value)))[0]
    return float(value)


def decode_value(param_type: int, wire: float) -> float:
    """The number a PARAM_SET carries (INT32 types: bytewise from the float field)."""
    if param_type == mavlink.MAV_PARAM_TYPE_INT32:
        return float(struct.unpack("<i", struct.pack("<f", wire))[0])
    return float(wire)


def _param_id(raw: Any) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("utf-8", "replace")
    return str(raw).split("\x00", 1)[0]


class ParamServer:
    """Parameter values of one vehicle, their persistence, and the MAVLink protocol."""

    def __init__(self, link: LinkOps, path: Path | str | None,
                 on_change: Callable[[str, float], None] | None = None) -> None:
        self.link = link
        self.path = None if path is None else Path(path)
        self.on_change = on_change
        self.counters: Counter[str] = Counter()
        self.values: dict[str, float] = table.defaults()
        self._names = [p.name for p in table.PARAMS]
        self._persistent: dict[str, float] = {}  # what the file holds: set by a GCS
        self._load()
        self._overridden: set[str] = set()

    # ------------------------------------------------------------------ store
    def _load(self) -> None:
        if self.path is None or not self.path.exists():
            return
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
            if not isinstance(data, dict) or data.get("format") != FILE_FORMAT or \
                    not isinstance(data.get("params"), dict):
                raise ValueError(f"not a {FILE_FORMAT} file")
        except (OSError, ValueError) as exc:  # JSONDecodeError is a ValueError
            self.counters["load_error"] += 1
            log.error("parameter file %s unreadable (%s): using defaults", self.path, exc)
            return
        for name, value in data["params"].items():
            try:
                self.values[name] = self._persistent[name] = table.check(name, value)
            except ValueError as exc:
                self.counters["load_skipped"] += 1
                log.error("parameter file %s: skipped: %s", self.path, exc)

    def save(self) -> None:
        """Write the values a ground station set (this run's and the file's earlier
        ones; not defaults, not overrides) to :attr:`path` atomically (no-op when None)."""
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        text = json.dumps({"format": FILE_FORMAT, "params": self._persistent}, indent=1,
                          sort_keys=True)
        fd, tmp = tempfile.mkstemp(prefix=self.path.name + ".", suffix=".tmp",
                                   dir=self.path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(text + "\n")
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    def set(self, name: str, value: float) -> float:
        """Validate, store, persist and report one value; ValueError if refused."""
        v = table.check(name, value)
        old = self.values[name]
        self.values[name] = v
        self._persistent[name] = v
        if v != old:
            try:
                self.save()
            except OSError as exc:
                self.counters["save_error"] += 1
                log.error("could not save parameters to %s: %s", self.path, exc)
                self.link.statustext(f"Param save failed: {exc}"[:50], "error")
            if self.on_change is not None:
                self.on_change(name, v)
        return v

    def override(self, name: str, value: float) -> float:
        """Set a value for this run only (command line): validated, never written to
        the file (a later save keeps the file's value), no ``on_change``; ValueError if
        refused."""
        v = table.check(name, value)
        self.values[name] = v
        self._overridden.add(name)
        return v

    def explicit(self) -> dict[str, float]:
        """The values somebody chose -- in the file, set by a ground station, or
        overridden for this run -- as opposed to defaults nobody touched. These are
        what the nodes must be told (a node's own ``--param`` stands for the rest)."""
        names = set(self._persistent) | self._overridden
        return {n: self.values[n] for n in self._names if n in names}

    # ------------------------------------------------------------------ protocol
    def value_message(self, name: str) -> Any:
        """PARAM_VALUE for ``name`` (its current value, index and the table's count)."""
        p = table.BY_NAME[name]
        return mavlink.MAVLink_param_value_message(
            name.encode("ascii"), encode_value(p.kind, self.values[name]), PARAM_TYPE[p.kind],
            len(self._names), self._names.index(name))

    def on_request_list(self, msg: Any, now: float, partner: object = None) -> list[Any]:
        self.counters["list"] += 1
        return [self.value_message(n) for n in self._names]

    def on_request_read(self, msg: Any, now: float, partner: object = None) -> list[Any]:
        name = _param_id(msg.param_id)
        if msg.param_index >= 0:
            name = self._names[msg.param_index] if msg.param_index < len(self._names) else ""
        if name not in table.BY_NAME:
            self.counters["read_unknown"] += 1
            what = name or f"index {msg.param_index}"
            self.link.statustext(f"Param read: unknown {what}"[:50], "warning")
            return []
        self.counters["read"] += 1
        return [self.value_message(name)]

    def on_set(self, msg: Any, now: float, partner: object = None) -> list[Any]:
        name = _param_id(msg.param_id)
        p = table.BY_NAME.get(name)
        if p is None:
            self.counters["set_unknown"] += 1
            self.link.statustext(f"Param set: unknown {name}"[:50], "warning")
            return []
        if msg.param_type != PARAM_TYPE[p.kind]:
            self.counters["set_wrong_type"] += 1
            self.link.statustext(f"Param {name}: wrong type {msg.param_type}"[:50], "warning")
            return [self.value_message(name)]
        try:
            self.set(name, decode_value(msg.param_type, msg.param_value))
        except ValueError as exc:
            self.counters["set_invalid"] += 1
            self.link.statustext(f"Param {exc}"[:50], "warning")
            return [self.value_message(name)]
        self.counters["set"] += 1
        self.link.broadcast(self.value_message(name))
        return []
