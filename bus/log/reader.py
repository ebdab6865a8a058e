"""Read episode logs (see :mod:`bus.log.writer`) robustly: episodes, incomplete ones, damage.

The reader scans the MCAP records itself (no index needed, so a crashed run without a
summary reads too) and never raises on damaged content: it validates every chunk's
CRC and sizes, skips what does not check out, resynchronises after a record whose
length is broken (on the next chunk or metadata record that parses and checks out),
stops at a truncated tail, and accounts for all of it in :class:`ReadReport`.

Episodes: messages of ``/skyloop/<vehicle>/...`` between that vehicle's START and END
``EpisodeEvent`` (both included). An episode is *complete* when it has both events, no
damaged region fell inside it, and its message count matches the ``skyloop.episode``
metadata record the writer left (when present). Messages outside any episode (actor
weights between episodes, for example) are counted in ``outside_episodes``.
"""

from __future__ import annotations

import mmap
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bus.keys import parse_ros_topic
from bus.log.mcap_scan import (
    CHANNEL,
    CHUNK,
    FOOTER,
    MAGIC,
    MAX_OP,
    MESSAGE,
    METADATA,
    SCHEMA,
    STATISTICS,
    U16,
    U64,
    Corrupt,
    chunk_records,
    num,
    records,
    resync,
    string,
    string_map,
)
from bus.messages import END, EPISODE_EVENT, START, decode, outcome_name

#: Name of the MCAP metadata record the writer leaves at each episode end.
EPISODE_METADATA = "skyloop.episode"


class LogReadError(Exception):
    """The path is not a readable episode log (missing, no ``.mcap`` in the directory)."""


@dataclass
class LoggedMessage:
    """One message of the log: ROS 2 topic, type, times (ns) and CDR bytes."""

    topic: str
    msgtype: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes
    vehicle: str | None = None
    name: str | None = None  # the skyloop topic name ("odom", "lidar/points", ...)

    def decode(self) -> Any:
        """The message object (raises if the CDR does not decode)."""
        return decode(self.msgtype, self.data)


@dataclass
class Episode:
    """The messages of one episode of one vehicle, in file order."""

    vehicle: str | None
    index: int
    start_event: Any | None = None
    end_event: Any | None = None
    messages: list[LoggedMessage] = field(default_factory=list)
    seen: int = 0  # messages in the episode, kept or filtered out
    expected: int | None = None  # from the writer's skyloop.episode record
    damaged: bool = False  # a skipped region fell inside the episode

    @property
    def complete(self) -> bool:
        """START and END present, nothing skipped inside, counts agree."""
        return (self.start_event is not None and self.end_event is not None
                and not self.damaged and (self.expected is None or self.expected == self.seen))

    @property
    def problem(self) -> str:
        """Why the episode is incomplete (``''`` if complete)."""
        if self.start_event is None:
            return "no START event (lost)"
        if self.end_event is None:
            return "no END event (run stopped or data lost)"
        if self.damaged:
            return "damaged data inside the episode"
        if self.expected is not None and self.expected != self.seen:
            return f"{self.seen} of {self.expected} messages"
        return ""

    @property
    def outcome(self) -> str | None:
        """success, collision, timeout, aborted; ``None`` without an END event."""
        return None if self.end_event is None else outcome_name(self.end_event)

    @property
    def steps(self) -> int | None:
        return None if self.end_event is None else int(self.end_event.steps)

    @property
    def seed(self) -> int | None:
        return None if self.start_event is None else int(self.start_event.seed)

    def topic(self, name: str) -> list[LoggedMessage]:
        """The episode's messages on skyloop topic ``name`` (e.g. ``'odom'``)."""
        return [m for m in self.messages if m.name == name]


@dataclass
class ReadReport:
    """What was read and what was lost; filled in while iterating."""

    path: Path
    file_bytes: int = 0
    messages: int = 0
    chunks: int = 0
    corrupt_chunks: int = 0
    corrupt_records: int = 0
    skipped_bytes: int = 0  # bytes passed over: bad chunks, broken records, cut tail
    truncated: bool = False  # ends inside a record
    finished: bool = False  # footer reached: the writer closed the file
    unknown_channel: int = 0  # messages whose channel definition was lost
    bad_events: int = 0  # episode events that do not decode
    outside_episodes: int = 0
    episodes_complete: int = 0
    episodes_incomplete: int = 0
    summary_messages: int | None = None  # from the MCAP statistics, if finished
    errors: list[str] = field(default_factory=list)

    @property
    def messages_lost(self) -> int | None:
        """Messages the summary lists but the scan did not deliver (finished files)."""
        return None if self.summary_messages is None else self.summary_messages - self.messages

    @property
    def clean(self) -> bool:
        """Finished, nothing skipped, no incomplete episode."""
        return (self.finished and not self.errors and self.skipped_bytes == 0
                and self.corrupt_records == 0 and self.episodes_incomplete == 0)

    def summary(self) -> str:
        """One line for logs and CLIs."""
        return (f"{self.path.name}: {self.episodes_complete} complete, "
                f"{self.episodes_incomplete} incomplete episode(s), {self.messages} messages"
                f"{'' if self.finished else ', not finished (no footer)'}"
                f"{', truncated' if self.truncated else ''}"
                f"{f', {self.corrupt_chunks} corrupt chunk(s)' if self.corrupt_chunks else ''}"
                f"{f', {self.skipped_bytes} bytes skipped' if self.skipped_bytes else ''}"
                f"{''.join(', ' + e for e in self.errors)}")


def log_files(run_dir: str | Path) -> list[Path]:
    """The ``*.mcap`` files of a run directory in the order written (``run_0``,
    ``run_1``, ..., ``run_10``: by the number after the last underscore)."""
    def number(path: Path) -> tuple[int, str]:
        tail = path.stem.rsplit("_", 1)[-1]
        return (int(tail) if tail.isdigit() else -1, path.name)

    return sorted(Path(run_dir).glob("*.mcap"), key=number)


class EpisodeLogReader:
    """Iterate a run's log: ``messages()`` in file order, ``episodes()`` grouped.

    ``path``: an ``.mcap`` file, or a run directory holding one (a split run's files are
    read one by one: :func:`log_files`). The
    :attr:`report` is complete once an iteration has finished.
    """

    def __init__(self, path: str | Path) -> None:
        p = Path(path)
        if p.is_dir():
            files = log_files(p)
            if len(files) != 1:
                raise LogReadError(f"{p} holds {len(files)} .mcap files"
                                   + (" (a split run: read each, bus.log.reader.log_files)"
                                      if files else ""))
            p = files[0]
        elif not p.exists():
            raise LogReadError(f"{p} does not exist")
        self.path = p
        self.report = ReadReport(path=p)
        self._schemas: dict[int, str] = {}
        self._channels: dict[int, tuple[str, str]] = {}  # id -> (topic, msgtype)
        self._episode_counts: dict[tuple[str | None, int], int] = {}
        self._damage = 0  # bumps on every skipped region (episodes compare)

    # ------------------------------------------------------------------ raw scan
    def messages(self) -> Iterator[LoggedMessage]:
        """Every readable message in file order (damage is skipped and reported)."""
        self._reset()
        return self._messages()

    def _reset(self) -> None:
        self.report = ReadReport(path=self.path)
        self._schemas.clear()
        self._channels.clear()
        self._episode_counts.clear()
        self._damage = 0

    def _messages(self) -> Iterator[LoggedMessage]:
        rep = self.report
        with open(self.path, "rb") as f:
            size = rep.file_bytes = f.seek(0, 2)
            if size < len(MAGIC) or f.seek(0) != 0 or f.read(len(MAGIC)) != MAGIC:
                rep.errors.append("not an MCAP file (bad magic)")
                return
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as buf:
                yield from self._scan(buf, len(MAGIC), size)

    def _scan(self, buf: Any, off: int, end: int) -> Iterator[LoggedMessage]:
        rep = self.report
        while off < end and not rep.finished:
            if off + 9 > end:
                rep.truncated, rep.skipped_bytes = True, rep.skipped_bytes + end - off
                self._damage += 1
                return
            op, n = buf[off], U64.unpack_from(buf, off + 1)[0]
            body, stop = off + 9, off + 9 + n
            if op == 0 or op > MAX_OP or stop > end:
                nxt = resync(buf, off + 1, end)
                rep.corrupt_records += 1
                self._damage += 1
                if nxt is None:
                    rep.truncated = stop > end and 0 < op <= MAX_OP
                    rep.skipped_bytes += end - off
                    return
                rep.skipped_bytes += nxt - off
                off = nxt
                continue
            try:
                if op == CHUNK:
                    rep.chunks += 1
                    raw = chunk_records(buf, body, stop)
                    yield from list(self._inner(raw))  # whole chunk checks out, or none
                elif op in (SCHEMA, CHANNEL, MESSAGE):
                    yield from self._inner_one(op, buf, body, stop)
                elif op == METADATA:
                    self._metadata(buf, body, stop)
                elif op == STATISTICS:
                    rep.summary_messages = num(U64, buf, body, stop)[0]
                elif op == FOOTER:
                    rep.finished = True
            except Corrupt as err:
                rep.corrupt_chunks += op == CHUNK
                rep.corrupt_records += op != CHUNK
                rep.skipped_bytes += stop - off
                self._damage += 1
                if len(rep.errors) < 20:
                    rep.errors.append(f"record at byte {off} skipped: {err}")
            off = stop

    def _inner(self, raw: bytes) -> Iterator[LoggedMessage]:
        for op, body, stop in records(raw, 0, len(raw)):
            yield from self._inner_one(op, raw, body, stop)

    def _inner_one(self, op: int, buf: Any, off: int, end: int) -> Iterator[LoggedMessage]:
        if op == SCHEMA:
            sid, o = num(U16, buf, off, end)
            self._schemas[sid] = string(buf, o, end)[0]
        elif op == CHANNEL:
            cid, o = num(U16, buf, off, end)
            sid, o = num(U16, buf, o, end)
            topic, o = string(buf, o, end)
            self._channels[cid] = (topic, self._schemas.get(sid, ""))
        elif op == MESSAGE:
            if off + 22 > end:
                raise Corrupt("message record too short")
            cid = U16.unpack_from(buf, off)[0]
            log_t, pub_t = U64.unpack_from(buf, off + 6)[0], U64.unpack_from(buf, off + 14)[0]
            chan = self._channels.get(cid)
            self.report.messages += 1
            if chan is None:
                self.report.unknown_channel += 1
                return
            topic, msgtype = chan
            try:
                vehicle, name = parse_ros_topic(topic)
            except ValueError:
                vehicle = name = None
            yield LoggedMessage(topic, msgtype, log_t, pub_t, bytes(buf[off + 22:end]),
                                vehicle, name)

    def _metadata(self, buf: Any, off: int, end: int) -> None:
        name, o = string(buf, off, end)
        data, _ = string_map(buf, o, end)
        if name == EPISODE_METADATA:
            try:
                key = (data.get("vehicle") or None, int(data["episode"]))
                self._episode_counts[key] = int(data["messages"])
            except (KeyError, ValueError):
                self.report.corrupt_records += 1

    # ------------------------------------------------------------------ episodes
    def episodes(self, *, include_incomplete: bool = False,
                 topics: Collection[str] | None = None) -> Iterator[Episode]:
        """Episodes in the order they end. ``topics`` (skyloop names, e.g. ``{'odom',
        'cmd_vel'}``) limits which messages are kept (all are counted). Incomplete
        episodes are counted in the report and yielded only if ``include_incomplete``."""
        keep = None if topics is None else set(topics)
        self._reset()
        rep = self.report
        open_eps: dict[str | None, tuple[Episode, int]] = {}  # vehicle -> (ep, damage mark)

        def close(ep: Episode, mark: int) -> Iterator[Episode]:
            ep.damaged = ep.damaged or mark != self._damage
            ep.expected = self._episode_counts.get((ep.vehicle, ep.index))
            if ep.complete:
                rep.episodes_complete += 1
            else:
                rep.episodes_incomplete += 1
            if ep.complete or include_incomplete:
                yield ep

        for msg in self._messages():
            event = None
            if msg.msgtype == EPISODE_EVENT:
                try:
                    event = msg.decode()
                except Exception:  # noqa: BLE001 - counted, treated as plain data
                    rep.bad_events += 1
            if event is not None and event.event == START:
                if msg.vehicle in open_eps:
                    yield from close(*open_eps.pop(msg.vehicle))
                open_eps[msg.vehicle] = (Episode(msg.vehicle, int(event.episode),
                                                 start_event=event), self._damage)
            current = open_eps.get(msg.vehicle)
            if current is None and event is not None and event.event == END:
                current = (Episode(msg.vehicle, int(event.episode)), self._damage)
                open_eps[msg.vehicle] = current
            if current is None:
                rep.outside_episodes += 1
                continue
            ep = current[0]
            ep.seen += 1
            if keep is None or msg.name in keep:
                ep.messages.append(msg)
            if event is not None and event.event == END:
                ep.end_event = event
                yield from close(*open_eps.pop(msg.vehicle))
        for ep, mark in list(open_eps.values()):
            yield from close(ep, mark)


def read_episodes(path: str | Path, *, include_incomplete: bool = False,
                  topics: Collection[str] | None = None) -> tuple[list[Episode], ReadReport]:
    """All episodes of a log and the report (see :meth:`EpisodeLogReader.episodes`)."""
    reader = EpisodeLogReader(path)
    eps = list(reader.episodes(include_incomplete=include_incomplete, topics=topics))
    return eps, reader.report
