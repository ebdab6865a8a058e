"""The episode log: MCAP files with ROS 2 schemas, in a rosbag2 directory.

Layout: ``<out_dir>/<run>/<run>_0.mcap`` (and ``_1``, ``_2``, ... when split every N
episodes or M minutes) plus ``metadata.yaml`` (rosbag2 version 5, the
format ROS 2 Humble writes, storage ``mcap``), so ``ros2 bag info/play <run>``,
``rosbags`` (the directory or the ``.mcap`` itself), Foxglove and the ``mcap`` CLI all
open it. MCAP profile ``ros2``, schema encoding ``ros2msg`` (the full concatenated
``.msg`` text), message encoding ``cdr``, chunks compressed with zstd (the default, at
:data:`ZSTD_LEVEL`; lz4 or none on request: ``compression``).

Crash safety (a SIGKILL loses at most the episode in progress):

- Each episode starts a fresh chunk and its END event closes it: at END the writer
  appends a ``skyloop.episode`` metadata record (vehicle, episode, outcome, steps,
  message count), then writes the chunk and flushes the file to the OS. Everything
  up to the last finished episode is therefore on disk, as complete records.
- Chunks also close when they reach ``chunk_size``; chunk CRCs are on.
- Schema and channel records are written twice: inside the chunk (where MCAP readers
  expect them) and at the top level of the data section, so a reader that skips one
  corrupt chunk still knows every channel.
- ``metadata.yaml`` and the MCAP summary (indexes, statistics) are written on
  :meth:`EpisodeLogWriter.close`. A crashed run has neither; :mod:`bus.log.reader`
  reads it by scanning, and ``rosbags`` reads the ``.mcap`` file itself by scanning too
  (as long as the tail is not cut inside a record).

The reader (episodes, incomplete and corrupt accounting) is :mod:`bus.log.reader`,
re-exported here.
"""

from __future__ import annotations

import functools
import math
import os
import re
import socket
import time
from collections import defaultdict
from collections.abc import Callable
from io import StringIO
from pathlib import Path
from typing import Any, BinaryIO

import mcap.writer
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, Schema
from mcap.writer import CompressionType, Writer
from ruamel.yaml import YAML

from bus.keys import parse_ros_topic, ros_topic
from bus.log.reader import (
    EPISODE_METADATA,
    Episode,
    EpisodeLogReader,
    LoggedMessage,
    LogReadError,
    ReadReport,
    read_episodes,
)
from bus.messages import END, EPISODE_EVENT, START, decode, encode, msgdef, outcome_name
from bus.ros.view import latched

__all__ = ["EpisodeLogWriter", "Episode", "EpisodeLogReader", "LoggedMessage", "LogReadError",
           "ReadReport", "read_episodes", "recover_log", "default_run_name", "EPISODE_METADATA"]

PROFILE = "ros2"
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
RUN_METADATA = "skyloop.run"
LIBRARY = "skyloop.bus.log.writer"
_COMPRESSION = {"none": CompressionType.NONE, "zstd": CompressionType.ZSTD,
                "lz4": CompressionType.LZ4}
#: Offered QoS written per topic (ROS 2 Humble string format): reliable, volatile,
#: keep last 10; the profile a default ROS 2 publisher offers.
_QOS_YAML = (
    "- history: 1\n  depth: 10\n  reliability: 1\n  durability: 2\n"
    "  deadline:\n    sec: 0\n    nsec: 0\n  lifespan:\n    sec: 0\n    nsec: 0\n"
    "  liveliness: 1\n  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n"
    "  avoid_ros_namespace_conventions: false"
)
#: The same for latched topics (``bus.ros.view.latched``: ``/tf_static``, the world and
#: goal markers): reliable, transient local, keep last 1, as tf2's static broadcaster
#: offers ``/tf_static``; ``ros2 bag play`` offers them so, and late subscribers get them.
_QOS_LATCHED_YAML = _QOS_YAML.replace("depth: 10", "depth: 1").replace("durability: 2",
                                                                         "durability: 1")
_RUN_NAME_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")
#: The zstd level of the log's chunks. On the stack's logs (XYZIR scans, valley, city
#: and forest) level -3 compresses 3.3-4.6x faster than zstandard's default 3 (about 0.06
#: instead of 0.21 ms of the recorder's CPU a lockstep step) for chunks 5-6% larger
#: (0.59-0.62 of the raw size instead of 0.56-0.59); decompression is 3x faster too.
#: Levels between -1 and -12 do not order by size on these 18-byte points (-1, -4, -6
#: to -9 and -12 were 7-40% larger than -3): benchmarks/RESULTS.md, 2026-12-03.
ZSTD_LEVEL = -3


class _McapZstd:
    """Stands in for the ``zstandard`` module in ``mcap.writer``, whose chunks go
    through ``zstandard.compress(data)`` at the library's level 3 with no option to
    change it: ``compress`` at :data:`ZSTD_LEVEL`, everything else the module's. Every
    MCAP writer of a process that imports this module writes zstd chunks so; readers
    need nothing (the level is not part of the format)."""

    def __init__(self, module: Any) -> None:
        self.module = module

    def compress(self, data: Any, level: int | None = None) -> bytes:
        return self.module.ZstdCompressor(
            level=ZSTD_LEVEL if level is None else level).compress(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.module, name)


if getattr(mcap.writer, "zstandard", None) is not None and \
        not isinstance(mcap.writer.zstandard, _McapZstd):
    mcap.writer.zstandard = _McapZstd(mcap.writer.zstandard)


def default_run_name() -> str:
    """``run-YYYYmmdd-HHMMSS-<pid>`` (local time)."""
    return time.strftime("run-%Y%m%d-%H%M%S") + f"-{os.getpid()}"


class EpisodeLogWriter:
    """Write one run to ``<out_dir>/<run_name>/<run_name>_0.mcap`` (``_1``, ``_2``, ...
    with ``split_episodes`` or ``split_minutes``).

    ``write(topic, msgtype, data, log_time_ns)`` takes CDR bytes on a ROS 2 topic name
    (``/skyloop/<vehicle>/<topic>``); ``write_msg(vehicle, topic, msg, ...)`` encodes a
    message first. Episode boundaries are taken from the ``skyloop_msgs/EpisodeEvent``
    messages written (see the module docstring). ``split_episodes`` N > 0: after N
    episodes have ended in a file and none is open, the file is finished (summary,
    footer, ``metadata.yaml`` rewritten) and the next one begins, as rosbag2's
    ``max_bag_duration`` splits a bag: a file never splits an episode, and a writer that
    dies loses at most its open file's tail. ``split_minutes`` M > 0: the same at the
    first episode boundary (an END with no episode open) once M minutes of ``clock``
    (seconds; default ``time.monotonic``, wall time) have passed since the open file
    began; with both, whichever comes first. ``compression``: of each MCAP chunk,
    ``"zstd"`` (default), ``"lz4"`` or ``"none"``; :mod:`bus.log.reader`, ``rosbags``
    and ``mcap``'s reader read all three (tested). Not thread-safe: one writer thread.
    """

    def __init__(self, out_dir: str | os.PathLike[str], run_name: str | None = None, *,
                 chunk_size: int = 2 * 1024 * 1024, compression: str = "zstd",
                 fsync: bool = False, metadata: dict[str, str] | None = None,
                 split_episodes: int = 0, split_minutes: float = 0.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        run_name = run_name or default_run_name()
        if not _RUN_NAME_RE.match(run_name):
            raise ValueError(f"run name must match {_RUN_NAME_RE.pattern}: {run_name!r}")
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}")
        if split_episodes < 0:
            raise ValueError(f"split_episodes must be >= 0, got {split_episodes}")
        if not (math.isfinite(split_minutes) and split_minutes >= 0):
            raise ValueError(f"split_minutes must be a finite number >= 0, got {split_minutes}")
        self.run_name = run_name
        self.dir = Path(out_dir) / run_name
        self.dir.mkdir(parents=True, exist_ok=False)
        self._fsync = fsync
        self._chunk_size, self._compression = chunk_size, _COMPRESSION[compression]
        self.split_episodes = split_episodes
        self.split_s = split_minutes * 60.0
        self._clock = clock
        self.counts: dict[str, int] = defaultdict(int)  # topic -> messages written
        self._types: dict[str, str] = {}  # topic -> msgtype, over every file
        self.first_ns: int | None = None
        self.last_ns = 0
        self.files: list[dict[str, Any]] = []  # rosbag2 "files" entries, one per file
        self._open_eps: dict[str | None, tuple[int, int]] = {}  # vehicle -> (episode, count)
        self.episodes_started = self.episodes_ended = self.bad_events = 0
        self.closed = False
        self._run_meta = {"run": run_name, "host": socket.gethostname(),
                          "pid": str(os.getpid()), "started_unix_ns": str(time.time_ns()),
                          **(metadata or {})}
        self._open_file()

    def _open_file(self) -> None:
        """Begin file ``<run>_<k>.mcap``: its own schemas and channels, the run metadata."""
        self.path = self.dir / f"{self.run_name}_{len(self.files)}.mcap"
        self._file: BinaryIO = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, chunk_size=self._chunk_size,
                              compression=self._compression, enable_crcs=True)
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}  # topic -> (channel id, msgtype)
        self._between_files = False
        self.files.append({"path": self.path.name, "first_ns": None, "last_ns": 0,
                           "message_count": 0, "episodes": 0})
        self._file_began = self._clock()  # split_minutes counts from here
        self._writer.add_metadata(RUN_METADATA, {**self._run_meta,
                                                 "file": str(len(self.files) - 1)})
        self._file.flush()

    # ------------------------------------------------------------------ channels
    def _top_level(self, record: Schema | Channel) -> None:
        """Write a copy of a schema/channel record between chunks (see module doc)."""
        builder = RecordBuilder()
        record.write(builder)
        self._file.write(builder.end())

    def _channel(self, topic: str, msgtype: str) -> int:
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != msgtype:
                raise ValueError(f"{topic} was {known[1]}, now {msgtype}")
            return known[0]
        self._writer.flush()  # close the open chunk so the copies sit between chunks
        schema_id = self._schemas.get(msgtype)
        if schema_id is None:
            text = msgdef(msgtype).encode()
            schema_id = self._writer.register_schema(msgtype, SCHEMA_ENCODING, text)
            self._schemas[msgtype] = schema_id
            self._top_level(Schema(id=schema_id, name=msgtype, encoding=SCHEMA_ENCODING,
                                   data=text))
        meta = {"offered_qos_profiles": _qos(topic)}
        channel_id = self._writer.register_channel(topic, MESSAGE_ENCODING, schema_id, meta)
        self._top_level(Channel(id=channel_id, schema_id=schema_id, topic=topic,
                                message_encoding=MESSAGE_ENCODING, metadata=meta))
        self._channels[topic] = (channel_id, msgtype)
        return channel_id

    # ------------------------------------------------------------------ writing
    def write(self, topic: str, msgtype: str, data: bytes, log_time_ns: int,
              publish_time_ns: int | None = None) -> None:
        """Append one CDR message on ROS 2 topic ``topic``."""
        if self.closed:
            raise RuntimeError("writer is closed")
        if self._between_files:
            self._open_file()
        channel_id = self._channel(topic, msgtype)
        vehicle = _vehicle_of(topic)
        event = None
        if msgtype == EPISODE_EVENT:
            try:
                event = decode(EPISODE_EVENT, data)
            except Exception:  # noqa: BLE001 - logged as data, boundary not marked
                self.bad_events += 1
            if event is not None and event.event == START:
                self._end_open(vehicle)
                self._writer.flush()  # the episode starts a fresh chunk
                self._open_eps[vehicle] = (int(event.episode), 0)
                self.episodes_started += 1
        self._writer.add_message(channel_id, log_time_ns, data,
                                 log_time_ns if publish_time_ns is None else publish_time_ns)
        self.counts[topic] += 1
        self._types[topic] = msgtype
        self.first_ns = log_time_ns if self.first_ns is None else min(self.first_ns, log_time_ns)
        self.last_ns = max(self.last_ns, log_time_ns)
        f = self.files[-1]
        f["first_ns"] = log_time_ns if f["first_ns"] is None else min(f["first_ns"], log_time_ns)
        f["last_ns"] = max(f["last_ns"], log_time_ns)
        f["message_count"] += 1
        if vehicle in self._open_eps:
            ep, n = self._open_eps[vehicle]
            self._open_eps[vehicle] = (ep, n + 1)
        if event is not None and event.event == END:
            self._finish_episode(vehicle, event)

    def write_msg(self, vehicle: str, topic: str, msg: Any, log_time_ns: int | None = None,
                  publish_time_ns: int | None = None) -> None:
        """Encode ``msg`` and append it on ``/skyloop/<vehicle>/<topic>``."""
        t = time.time_ns() if log_time_ns is None else log_time_ns
        self.write(ros_topic(vehicle, topic), msg.__msgtype__, encode(msg), t, publish_time_ns)

    def _end_open(self, vehicle: str | None) -> None:
        """A START while an episode is open: the old one stays incomplete (no END)."""
        self._open_eps.pop(vehicle, None)

    def _finish_episode(self, vehicle: str | None, event: Any) -> None:
        episode, count = self._open_eps.pop(vehicle, (int(event.episode), -1))
        self.episodes_ended += 1
        # The metadata record goes out before the chunk holding the episode's tail, so a
        # reader meets the expected count before the END event it checks it against.
        self._writer.add_metadata(EPISODE_METADATA, {
            "vehicle": vehicle or "", "episode": str(episode), "outcome": outcome_name(event),
            "steps": str(int(event.steps)), "messages": str(count)})
        self.flush()
        self.files[-1]["episodes"] += 1
        if not self._open_eps and self._split_due():
            self._finish_file()
            self._write_metadata_yaml()
            self._between_files = True  # the next file begins with the next message

    def _split_due(self) -> bool:
        """Whether the open file is full: ``split_episodes`` episodes ended in it, or
        ``split_minutes`` passed since it began (read at episode ends only)."""
        if self.split_episodes and self.files[-1]["episodes"] >= self.split_episodes:
            return True
        return bool(self.split_s) and self._clock() - self._file_began >= self.split_s

    def flush(self) -> None:
        """Close the open chunk and hand everything to the OS (``fsync`` if asked)."""
        if self._between_files:
            return
        self._writer.flush()
        if self._fsync:
            os.fsync(self._file.fileno())

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Write the MCAP summary and footer, then ``metadata.yaml`` (idempotent)."""
        if self.closed:
            return
        self.closed = True
        if not self._between_files:
            self._finish_file()
        self._write_metadata_yaml()

    def _finish_file(self) -> None:
        """The open file's summary and footer (MCAP ``finish``), flushed and closed."""
        self._writer.add_metadata("rosbag2", {"serialized_metadata": _yaml(self._bag_metadata())})
        self._writer.finish()
        self._file.flush()
        if self._fsync:
            os.fsync(self._file.fileno())
        self._file.close()

    def _write_metadata_yaml(self) -> None:
        tmp = self.dir / "metadata.yaml.tmp"
        tmp.write_text(_yaml({"rosbag2_bagfile_information": self._bag_metadata()}) + "\n")
        tmp.replace(self.dir / "metadata.yaml")

    @property
    def next_file_index(self) -> int:
        """The index of the file the next message goes to (a split run opens the next
        file with it)."""
        return len(self.files) if self._between_files else len(self.files) - 1

    @property
    def paths(self) -> list[Path]:
        """Every file of the run so far, in order."""
        return [self.dir / f["path"] for f in self.files]

    def _bag_metadata(self) -> dict[str, Any]:
        start = self.first_ns or 0
        duration = max(0, self.last_ns - start)
        info = {
            "version": 5,
            "storage_identifier": "mcap",
            "relative_file_paths": [f["path"] for f in self.files],
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": sum(self.counts.values()),
            "topics_with_message_count": [
                {"topic_metadata": {"name": topic, "type": msgtype,
                                    "serialization_format": MESSAGE_ENCODING,
                                    "offered_qos_profiles": _qos(topic)},
                 "message_count": self.counts[topic]}
                for topic, msgtype in self._types.items()],
            "compression_format": "",
            "compression_mode": "",
            "files": [{"path": f["path"],
                       "starting_time": {"nanoseconds_since_epoch": f["first_ns"] or 0},
                       "duration": {"nanoseconds": max(0, f["last_ns"] - (f["first_ns"] or 0))},
                       "message_count": f["message_count"]} for f in self.files],
        }
        return info

    def __enter__(self) -> EpisodeLogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def recover_log(src: str | os.PathLike[str], out_dir: str | os.PathLike[str] | None = None,
                run_name: str | None = None) -> tuple[Path, ReadReport]:
    """Rewrite what is readable of a crashed or damaged log as a finished one.

    A run killed before :meth:`EpisodeLogWriter.close` has no MCAP summary, footer or
    ``metadata.yaml``, which ``rosbags``, ``ros2 bag`` and the ``mcap`` tools need; this
    copies every readable message (incomplete episodes included, still without their
    END) into ``<out_dir>/<run_name>`` (default: next to the source run, named
    ``<run>-recovered``). Returns the new run directory and the read report.
    """
    reader = EpisodeLogReader(src)
    base = reader.path.parent
    out = Path(out_dir) if out_dir is not None else base.parent
    with EpisodeLogWriter(out, run_name or f"{base.name}-recovered",
                          metadata={"recovered_from": str(reader.path)}) as writer:
        for msg in reader.messages():
            writer.write(msg.topic, msg.msgtype, msg.data, msg.log_time_ns, msg.publish_time_ns)
    report = reader.report  # messages() reads no episodes: count those the copy has
    report.episodes_complete = writer.episodes_ended
    report.episodes_incomplete = writer.episodes_started - writer.episodes_ended
    return writer.dir, report


def _yaml(data: dict[str, Any]) -> str:
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    out = StringIO()
    yaml.dump(data, out)
    return out.getvalue().strip()


def _qos(topic: str) -> str:
    return _QOS_LATCHED_YAML if latched(topic) else _QOS_YAML


@functools.lru_cache(maxsize=1024)
def _vehicle_of(topic: str) -> str | None:
    try:
        return parse_ros_topic(topic)[0]
    except ValueError:
        return None
