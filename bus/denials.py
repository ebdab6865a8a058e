"""What the router's access control refuses, counted (``skyloop router``; issue 13 §4).

Zenoh counts the messages its access control drops only when built with its ``stats``
feature, which the eclipse-zenoh wheel is not (``bus/certs.py``). What the wheel does
have is Zenoh's log: at TRACE, the target :data:`ACL_TARGET` writes a line for every
decision. The router (a Python session, ``skyloop.cli.tools.run_router``) therefore
turns that target on (:func:`merged_filter`, the user's ``RUST_LOG`` kept), reads its
own log (:class:`StdoutTap`: the wheel's log goes to fd 1, ``tracing``'s default
writer, not to stderr) and counts the refusals (:class:`Denials`); every line the user's
own ``RUST_LOG`` would have shown is passed on unchanged, the rest (the decisions turned
on only to be counted) is read and dropped.

What zenoh 1.10.2 logs (measured, ``tests/bus/test_bus_security.py``):

* A message on a key expression its sender declared (a publisher's puts, the usual
  case): one line per message, ``Using cached result: <zid> is unauthorized to Put
  (ingress) on skyloop/uav1/cmd_vel`` (``authorized`` when allowed).
* A message on a key expression that was not declared (``session.put(key)``, a wildcard
  put, a query): one line per message and per ACL subject the session matched,
  ``<zid> on <subject> is unauthorized to Put (ingress) on <key>``. A skyloop session
  matches one subject (one certificate, one interface), so one line per message.
  A session that matches no subject (one on a ``tcp/`` link added to the router) is
  refused by the default permission with no line at all: not counted.
* When a key expression is first declared on a session, a block of the same
  ``<zid> on <subject> ...`` lines, one per message kind (``Query``, ``Reply``, ``Put``,
  ..., ``Declare Liveliness Subscriber``), after ``ACL (ingress): caching permissions
  for `<key>` ...``: the rights computed in advance, not messages, and not counted
  (:data:`CACHE_KINDS`, recognised by that order on the thread that logged the header).

A denial is counted once per refused message, by kind and direction
(:meth:`Denials.counters`: ``denied`` and e.g. ``denied_put_ingress``,
``denied_query_ingress``, ``denied_declare_liveliness_token_ingress``), and by key for
the router's last line (:meth:`Denials.summary`, at most :data:`KEYS_KEPT` keys).
A session that matches several subjects (a node named in ``router.json5`` matches the
CA's and its own) is decided subject by subject on an undeclared key: refusals, then
an allowance, for one allowed message; such lines count nothing, and a message refused
by all counts once (the number of subjects learned from the session's cache blocks).

The cost is the log (measured: 20,000 puts of a setpoint through ``skyloop router``,
one subscriber, the router's CPU time from ``/proc``, a loaded 2-core machine): a
refused put 10 us instead of 2, an allowed one 15 us instead of 6 (it logs two lines,
ingress and egress to the subscriber); of that, this module's parsing is about 3.5 us a
line, the rest Zenoh's formatting and the pipe. 1,000 messages a second through the
router: about 1.5% of a core.
"""

from __future__ import annotations

import collections
import os
import re
import sys
import threading
from typing import BinaryIO

#: the ``tracing`` target of Zenoh's access control
ACL_TARGET = "zenoh::net::routing::interceptor::access_control"
#: ``tracing``'s levels, by verbosity (``off`` shows nothing)
LEVELS = {"off": 0, "error": 1, "warn": 2, "info": 3, "debug": 4, "trace": 5}
TRACE = LEVELS["trace"]
#: the message kinds, in order, of the rights Zenoh computes when a key expression is
#: declared (``compute_keyexpr_cache``; one line each and per subject)
CACHE_KINDS = ("Query", "Reply", "Put", "Delete", "Declare/Undeclare Subscriber",
               "Declare/Undeclare Queryable", "Declare/Undeclare Liveliness Token",
               "Liveliness Query", "Declare Liveliness Subscriber")
#: how many distinct (kind, direction, key) the router's last line tells apart: a client
#: putting on ever new keys must not grow the router's memory
KEYS_KEPT = 100

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_LINE = re.compile(r"(?P<level>TRACE|DEBUG|INFO|WARN|ERROR) .*?ThreadId\((?P<thread>\d+)\) "
                   r"(?P<target>[\w:]+): (?P<msg>.*)")
_DECISION = (r"is (?P<verdict>authorized|unauthorized) to (?P<kind>.+) "
             r"\((?P<flow>ingress|egress)\) on (?P<key>.+)")
_CACHED = re.compile(r"Using cached result: \w+ " + _DECISION)
_SUBJECT = re.compile(r"(?P<zid>\w+) on .+? " + _DECISION)
_CACHING = re.compile(r"ACL \((?P<flow>ingress|egress)\): caching permissions for `(?P<key>.*)`")


def _directives(rust_log: str) -> list[tuple[str, str]]:
    """``(target, level)`` of each plain directive of an ``EnvFilter`` string (a bare
    level has target ``""``); directives with span or field filters are left out."""
    out = []
    for d in (d.strip() for d in rust_log.split(",")):
        if not d or "[" in d or "{" in d:
            continue
        target, _, level = d.rpartition("=") if "=" in d else ("", "", d)
        if level.lower() in LEVELS:
            out.append((target, level.lower()))
        elif not target:  # a bare target: every level of it
            out.append((d, "trace"))
    return out


def target_level(rust_log: str | None, target: str = ACL_TARGET) -> int:
    """The level (:data:`LEVELS`) at which ``rust_log`` (a ``RUST_LOG`` value, None:
    unset) shows ``target``'s events: its most specific directive whose target is a
    prefix of ``target`` (one without a target: any), else ``error`` (EnvFilter's
    default); unset shows nothing."""
    if not rust_log:
        return LEVELS["off"]
    best: tuple[int, int] | None = None  # (specificity, level)
    for t, level in _directives(rust_log):
        if target == t or target.startswith(t + "::") or not t:
            if best is None or len(t) >= best[0]:
                best = (len(t), LEVELS[level])
    return best[1] if best is not None else LEVELS["error"]


def merged_filter(rust_log: str | None) -> str:
    """A ``RUST_LOG`` filter that shows what ``rust_log`` shows (None: nothing) and the
    access control's decisions (:data:`ACL_TARGET` at TRACE): its directives kept, one
    naming that target exactly replaced."""
    kept = [d.strip() for d in (rust_log or "").split(",")
            if d.strip() and d.strip().split("=")[0] != ACL_TARGET]
    return ",".join([*kept, f"{ACL_TARGET}=trace"])


def _name(kind: str, flow: str) -> str:
    return "denied_" + re.sub(r"[^a-z]+", "_", kind.lower()).strip("_") + "_" + flow


class Denials:
    """Counts the refusals in Zenoh's access-control log, a line at a time (the module
    docstring): :meth:`feed` each line, :meth:`counters` at the end."""

    def __init__(self) -> None:
        self.total = 0
        self.by_kind: collections.Counter[str] = collections.Counter()  # denied_<kind>_<flow>
        self.by_key: collections.Counter[tuple[str, str, str]] = collections.Counter()
        self.other_keys = 0  # refusals on keys beyond KEYS_KEPT
        #: thread -> the cache block it is logging: [direction, key, next index of
        #: CACHE_KINDS, its last kind, how many lines of that kind]
        self._blocks: dict[str, list] = {}
        #: thread -> refusals by subject of one message not decided yet: [(zid, kind,
        #: direction, key), lines]; an ``authorized`` line next means a later subject
        #: allowed it
        self._runs: dict[str, list] = {}
        self._subjects: dict[str, int] = {}  # zid -> subjects it matches (cache blocks)
        self._lock = threading.Lock()

    def feed(self, line: str) -> int | None:
        """Count ``line`` if it is a refusal; its level (:data:`LEVELS`) if it is a line
        of :data:`ACL_TARGET`, else None (another target's line, or not a log line)."""
        m = _LINE.search(_ANSI.sub("", line).rstrip("\r\n"))
        if m is None or m["target"] != ACL_TARGET:
            return None
        thread, msg = m["thread"], m["msg"]
        with self._lock:
            if (d := _SUBJECT.match(msg)) is not None:
                self._by_subject(thread, d)
            else:  # a message decided from the cache, a block's header, or another line
                self._end_run(thread)
                self._blocks.pop(thread, None)
                if (c := _CACHING.match(msg)) is not None:
                    self._blocks[thread] = [c["flow"], c["key"], 0, None, 0]
                elif (d := _CACHED.match(msg)) is not None and d["verdict"] == "unauthorized":
                    self._count(d["kind"], d["flow"], d["key"])
        return LEVELS[m["level"].lower()]

    def _by_subject(self, thread: str, d: re.Match) -> None:
        """A ``<zid> on <subject> is ...`` line: part of a cache block, or one subject's
        decision on a message (the module docstring)."""
        zid = d["zid"]
        block = self._blocks.get(thread)
        if block is not None and self._in_block(block, d):
            self._subjects[zid] = max(self._subjects.get(zid, 1), block[4])
            return
        self._blocks.pop(thread, None)
        what = (zid, d["kind"], d["flow"], d["key"])
        run = self._runs.get(thread)
        if run is not None and run[0] != what:
            self._end_run(thread)
            run = None
        if d["verdict"] == "unauthorized":
            if run is None:
                self._runs[thread] = [what, 1]
            else:
                run[1] += 1
            return
        if run is not None:  # allowed by a later subject: the lines before it were its
            del self._runs[thread]  # own, but for whole refused messages before it
            n = self._subjects.get(zid)
            if n is None:
                self._subjects[zid] = run[1] + 1
            else:
                for _ in range(run[1] // n):
                    self._count(*what[1:])
        if len(self._subjects) > 10 * KEYS_KEPT:  # sessions come and go
            self._subjects.clear()

    def _end_run(self, thread: str) -> None:
        """The refusals of ``thread``'s run stand: one message per subject the session
        matches (1 if unknown: then at least as many as refused)."""
        if (run := self._runs.pop(thread, None)) is not None:
            (zid, kind, flow, key), lines = run
            n = self._subjects.get(zid, 1)
            for _ in range(-(-lines // n)):
                self._count(kind, flow, key)

    @staticmethod
    def _in_block(block: list, d: re.Match) -> bool:
        """Whether decision ``d`` is the next line of a cache block (the module
        docstring): same direction and key; the first kind first, then the last kind
        again (another subject) or a later one."""
        flow, key, at, last, _ = block
        kinds = CACHE_KINDS[:1] if at == 0 else CACHE_KINDS[at - 1:]
        if d["flow"] != flow or d["key"] != key or d["kind"] not in kinds:
            return False
        block[2] = CACHE_KINDS.index(d["kind"], max(at - 1, 0)) + 1
        block[4] = block[4] + 1 if d["kind"] == last else 1
        block[3] = d["kind"]
        return True

    def _count(self, kind: str, flow: str, key: str) -> None:
        self.total += 1
        self.by_kind[_name(kind, flow)] += 1
        k = (kind, flow, key)
        if k in self.by_key or len(self.by_key) < KEYS_KEPT:
            self.by_key[k] += 1
        else:
            self.other_keys += 1

    def finish(self) -> None:
        """Decide what is still open (the log has ended)."""
        with self._lock:
            for thread in list(self._runs):
                self._end_run(thread)

    def counters(self) -> dict[str, int]:
        """``denied`` (every refused message) and ``denied_<kind>_<direction>``."""
        self.finish()
        with self._lock:
            return {"denied": self.total, **dict(self.by_kind)}

    def summary(self) -> str:
        """One line: how many refused, by kind, direction and key (most first)."""
        self.finish()
        with self._lock:
            parts = [f"{kind} ({flow}) on {key} {n}"
                     for (kind, flow, key), n in self.by_key.most_common()]
            if self.other_keys:
                parts.append(f"other keys {self.other_keys}")
            return (f"access control refused {self.total} message(s)"
                    + (": " + ", ".join(parts) if parts else ""))


class StdoutTap:
    """This process's fd ``fd`` (the Zenoh wheel's log: fd 1) through a pipe that a
    daemon thread reads: each line is fed to ``denials``; a line of another target, or
    of :data:`ACL_TARGET` at a level up to ``show_level`` (what the user's ``RUST_LOG``
    would have shown), goes on unchanged to where ``fd`` went before. Python's own
    ``sys.stdout`` writes there directly. Start it before Zenoh's logging is
    initialised; :meth:`stop` reads what is left and restores ``fd``."""

    def __init__(self, denials: Denials, show_level: int, fd: int = 1) -> None:
        self.denials, self.show_level, self.fd = denials, show_level, fd
        self._saved: int | None = None
        self._thread: threading.Thread | None = None
        self._stdout = sys.stdout

    def start(self) -> None:
        sys.stdout.flush()
        self._saved = os.dup(self.fd)
        r, w = os.pipe()
        os.dup2(w, self.fd)
        os.close(w)
        if self.fd == 1:  # Python's prints (the counters line) straight out, in order
            self._stdout = sys.stdout
            sys.stdout = open(self._saved, "w", buffering=1, closefd=False)  # noqa: SIM115
        self._thread = threading.Thread(target=self._read, args=(os.fdopen(r, "rb"),),
                                        name="acl-log", daemon=True)
        self._thread.start()

    def _read(self, pipe: BinaryIO) -> None:
        out = self._saved
        assert out is not None
        for raw in pipe:  # never stops reading: a full pipe would stall Zenoh's threads
            try:
                level = self.denials.feed(raw.decode("utf-8", "replace"))
            except Exception:  # noqa: BLE001 - a line it cannot read is passed on, uncounted
                level = None
            if out >= 0 and (level is None or level <= self.show_level):
                try:
                    os.write(out, raw)  # one line: short writes do not happen on a tty/pipe
                except OSError:  # stdout gone (the launcher died): keep counting
                    out = -1
        pipe.close()

    def stop(self, timeout: float = 2.0) -> None:
        """Restore ``fd`` (the pipe's write end closes), read the rest of the pipe."""
        if self._saved is None:
            return
        sys.stdout.flush()
        os.dup2(self._saved, self.fd)
        if self.fd == 1:
            sys.stdout.close()
            sys.stdout = self._stdout
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():  # it may still write to the saved fd: leave it
                return
        os.close(self._saved)
        self._saved = None
