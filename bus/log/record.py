"""The recorder: every message under ``skyloop/**`` (or one vehicle's) into the MCAP log.

Zenoh's receive thread puts each sample into the subscriber's channel (no Python runs
there, no Python thread wakes per message); a receiving thread takes what the channel
holds every ``poll_s`` (:data:`POLL_S`, 5 ms) and copies the payloads, with the wall
time it took them (the log time: at most ``poll_s`` after arrival, plus scheduling),
into a bounded queue (a full queue is a *counted* drop; the channel itself holds up to
``max(queue_size, 64)`` samples and would hold Zenoh's receive back only if the
receiving thread stalled that long); one writer thread, woken once per batch, validates
each payload against its topic's type (an undecodable payload is counted, not written,
so the log stays readable by every tool) and appends it to the
:class:`~bus.log.writer.EpisodeLogWriter` under the ROS 2 topic ``/skyloop/<vehicle>/<topic>``.
Stopping undeclares the subscriber, takes what the channel still holds, drains the
queue, then finishes the file. Measured in a lockstep stack (issue 11, "Speed";
benchmarks/RESULTS.md 2026-12-03): the recorder's Python threads woke 1.4 times a step
instead of 7.3 (one Python callback and one writer wake-up per message before).

Episode ends are held back briefly: an episode's messages come from several processes
over separate Zenoh links, so the sim's END can overtake the last observation or
setpoint of that episode (seen under load: the episode then lacked its last observation
and was skipped when training from the log). The writer thread holds a vehicle's END
until that vehicle's next START arrives or ``end_grace_s`` (0.25 s) passes; step topics
(clock, odometry, truth, scan, observation, setpoint, step record) arriving meanwhile are
written before it, anything else (status, actor weights, ...) right after it, so between
episodes as before; a step message naming the next episode (perception's first
observation can overtake the sim's START the same way) waits for that START and is
written right after it; stopping writes what is held.

The log's 3D view (``view``, a :class:`~bus.ros.view.RosView`; ``skyloop record`` has
one unless ``--no-ros-view``): the writer thread hands each message it writes to the
view and writes what the view derives from it (``/tf``, ``/tf_static``, ``/clock``, the
world, goal, aircraft and icosahedron markers, the path; see :mod:`bus.ros.view`) just
before it, with the same log time, counted in ``derived`` (not ``written``, which stays
the bus messages). A world (built by a worker process, :class:`bus.ros.scene.WorldWorker`)
is written when ready; at stop the writer waits for it at most ``world_wait_s`` (1 s:
the launcher's stop grace is 3 s for every node), then the view closes its worker.

:func:`run_record` is what the ``skyloop record`` command runs (its flags:
``skyloop.cli.tools.RecordCommand``).
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from bus import keys
from bus.keys import key_all, msgtype, parse_key
from bus.log.writer import EpisodeLogWriter
from bus.messages import END, START, decode
from bus.node import RateLimitedLog
from bus.ros.view import RosView
from bus.session import SessionConfig, open_session

log = logging.getLogger("skyloop.record")
_STOP = object()
#: How often the receiving thread takes what Zenoh's channel holds (s). Taking in batches
#: (no Python callback per message) keeps the recorder's wake-ups off the stack's hops.
POLL_S = 0.005
#: The run's time convention, in the MCAP run metadata (docs/interfaces.md, "Logs in 3D").
TIME_METADATA = {
    "log_time": "wall clock when the recorder received the message (ns since the epoch)",
    "header_stamps": "stack time: sim seconds since the sim started (/clock carries it)",
}


@dataclass
class RecordResult:
    """Where the run went and what happened to the messages."""

    path: Path  # the run directory (MCAP file + metadata.yaml)
    counters: dict[str, int] = field(default_factory=dict)


class Recorder:
    """Subscribe ``skyloop/**`` (or ``skyloop/<vehicle>/**``) on ``session`` and write
    to ``writer`` from a background thread. Counters (:meth:`counters`): ``received``,
    ``written``, ``dropped`` (queue full), ``undecodable``, ``unknown_topic``,
    ``write_errors``, plus ``episodes_started``/``episodes_ended`` of the writer; with a
    ``view``: ``derived`` (messages it added), ``view_errors`` (derivations that
    raised), and its own ``other_vehicle`` and ``scene_errors``."""

    def __init__(self, session: zenoh.Session, writer: EpisodeLogWriter,
                 vehicle: str | None = None, queue_size: int = 512,
                 validate: bool = True, end_grace_s: float = 0.25,
                 view: RosView | None = None, world_wait_s: float = 1.0,
                 poll_s: float = POLL_S) -> None:
        self.writer = writer
        self.end_grace_s = end_grace_s
        self.validate = validate
        self.view = view
        self.world_wait_s = world_wait_s
        self.poll_s = poll_s
        self.queue_size = queue_size
        self._q: deque[Any] = deque()  # taken by the writer thread; bounded by _take
        self._cv = threading.Condition()
        self._lock = threading.Lock()
        self._counts = dict.fromkeys(("received", "written", "dropped", "undecodable",
                                      "unknown_topic", "write_errors", "derived",
                                      "view_errors"), 0)
        self._drop_log = RateLimitedLog(log, 5.0)
        self._bad_log = RateLimitedLog(log, 5.0)
        self._thread = threading.Thread(target=self._run, name="skyloop-record", daemon=True)
        self._thread.start()
        self.key_expr = key_all(vehicle)
        self._capacity = max(queue_size, 64)  # of Zenoh's channel
        self._sub: zenoh.Subscriber | None = session.declare_subscriber(
            self.key_expr, zenoh.handlers.FifoChannel(self._capacity))
        self._samples = self._sub.handler
        self._rx_stop = threading.Event()
        self._rx = threading.Thread(target=self._take_run, name="skyloop-record-rx",
                                    daemon=True)
        self._rx.start()
        self._stopped = False

    def _count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._counts[name] += n

    def _take_run(self) -> None:
        """The receiving thread: every ``poll_s``, take what Zenoh's channel holds (at
        once again while a take stops at its limit: the channel is filling faster)."""
        while not self._rx_stop.is_set():
            if not self._take():
                self._rx_stop.wait(self.poll_s)
        while self._take():  # what came before the subscriber was undeclared
            pass

    def _take(self) -> bool:
        """Take the samples waiting in Zenoh's channel, at most a channel's capacity:
        copy those the writer's queue has room for, with the time they were taken, into
        it, and count the rest dropped (not copied). True if it stopped at the limit;
        never raises."""
        got: list[tuple[str, bytes, int]] = []
        dropped, first_dropped, taken = 0, "", 0
        with self._cv:
            room = max(0, self.queue_size - len(self._q))
        try:
            try_recv = self._samples.try_recv
            while taken < self._capacity and (sample := try_recv()) is not None:
                taken += 1
                if len(got) < room:
                    got.append((str(sample.key_expr), sample.payload.to_bytes(),
                                time.time_ns()))
                else:
                    dropped += 1
                    first_dropped = first_dropped or str(sample.key_expr)
        except zenoh.ZError:  # empty and closed: the subscriber is undeclared
            pass
        except Exception:  # noqa: BLE001 - keep receiving
            dropped += 1
            self._drop_log(logging.ERROR, "recorder receive failed", exc_info=True)
        if got:
            with self._cv:
                self._q.extend(got)
                self._cv.notify()
        if got or dropped:
            with self._lock:
                self._counts["received"] += taken
                self._counts["dropped"] += dropped
        if first_dropped:
            self._drop_log(logging.WARNING, "recorder queue full: message on %s dropped",
                           first_dropped)
        return taken >= self._capacity

    def _run(self) -> None:
        # vehicle -> (held END, write-by time, messages that go after it, the ended
        # episode, the next episode's step messages that came before its START)
        pending: dict[str, tuple[Any, float, list[Any], int, list[Any]]] = {}

        def release(vehicle: str, start: Any = None) -> None:
            held, _, after, _, early = pending.pop(vehicle)
            for it in (held, *after, *([start] if start is not None else []), *early):
                self._write(it)

        q, cv = self._q, self._cv
        while True:
            with cv:
                if not q:
                    cv.wait(None if not pending else
                            max(0.0, min(p[1] for p in pending.values()) - time.monotonic()))
                item = q.popleft() if q else None
            now = time.monotonic()
            for vehicle in [v for v, p in pending.items() if p[1] <= now]:
                release(vehicle)
            if item is None:
                continue
            if item is _STOP:
                for vehicle in list(pending):
                    release(vehicle)
                self._finish_view()
                return
            event = _episode_event(item[0], item[1])
            if event is not None:
                vehicle, kind, episode = event
                if vehicle in pending:  # the next START: the held END goes first
                    if kind == START:
                        release(vehicle, start=item)  # then START, then what came early
                        continue
                    release(vehicle)
                if kind == END:
                    pending[vehicle] = (item, now + self.end_grace_s, [], episode, [])
                    continue
            else:
                vehicle, step_topic = _step_topic(item[0])
                if vehicle in pending:
                    held = pending[vehicle]
                    if not step_topic:  # not the episode's: after END
                        held[2].append(item)
                        continue
                    if _episode_of(item[0], item[1]) not in (None, held[3]):
                        held[4].append(item)  # the next episode's, ahead of its START
                        continue
            self._write(item)

    def _write(self, item: tuple[str, bytes, int]) -> None:
        key_expr, data, t_ns = item
        parsed = _parsed(key_expr)
        if parsed is None:
            self._count("unknown_topic")
            self._bad_log(logging.WARNING, "not a skyloop topic, not recorded: %s", key_expr)
            return
        vehicle, topic, kind = parsed
        if self.validate or self.view is not None:
            try:
                msg = decode(kind, data)
            except Exception as err:  # noqa: BLE001 - counted, not written
                if self.validate:
                    self._count("undecodable")
                    self._bad_log(logging.WARNING, "%s: payload does not decode as %s: %s",
                                  key_expr, kind, err)
                    return
            else:
                if self.view is not None:
                    self._derive(vehicle, topic, msg, t_ns)
        try:
            self.writer.write("/" + key_expr, kind, data, t_ns)
            self._count("written")
        except Exception:  # noqa: BLE001 - keep recording the rest
            self._count("write_errors")
            self._bad_log(logging.ERROR, "writing %s failed", key_expr, exc_info=True)

    def _derive(self, vehicle: str, topic: str, msg: Any, t_ns: int) -> None:
        """The view's messages derived from ``msg``, written before it (same log time)."""
        try:
            derived = self.view.derive(vehicle, topic, msg, self.writer.next_file_index)
        except Exception:  # noqa: BLE001 - the bus message is still written
            self._count("view_errors")
            self._bad_log(logging.ERROR, "log view failed on %s", topic, exc_info=True)
            return
        self._write_derived(derived, t_ns)

    def _write_derived(self, derived: list[tuple[str, str, bytes]], t_ns: int) -> None:
        for ros_name, kind, payload in derived:
            try:
                self.writer.write(ros_name, kind, payload, t_ns)
                self._count("derived")
            except Exception:  # noqa: BLE001 - keep recording the rest
                self._count("write_errors")
                self._bad_log(logging.ERROR, "writing %s failed", ros_name, exc_info=True)

    def _finish_view(self) -> None:
        """At stop: a world still being built gets ``world_wait_s`` to be written into
        the open file (not into a new one of a split run)."""
        view, w = self.view, self.writer
        if view is None or w.first_ns is None or w.next_file_index != len(w.files) - 1:
            return
        try:
            derived = view.finish(w.next_file_index, self.world_wait_s)
        except Exception:  # noqa: BLE001 - the file still closes
            self._count("view_errors")
            log.error("log view failed at stop", exc_info=True)
            return
        self._write_derived(derived, w.last_ns)

    def counters(self) -> dict[str, int]:
        """Snapshot of the counters."""
        with self._lock:
            out = dict(self._counts)
        if self.view is not None:
            out.update(self.view.counts_snapshot())
        out["queued"] = len(self._q)
        out["episodes_started"] = self.writer.episodes_started
        out["episodes_ended"] = self.writer.episodes_ended
        return out

    def wait_written(self, n: int, timeout: float = 10.0) -> bool:
        """Wait until ``n`` messages have been written (or ``timeout`` s pass)."""
        deadline = time.monotonic() + timeout
        while self.counters()["written"] < n:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.005)
        return True

    def stop(self, timeout: float = 30.0) -> dict[str, int]:
        """Undeclare the subscriber, drain the queue, finish the file; return counters."""
        if not self._stopped:
            self._stopped = True
            sub, self._sub = self._sub, None
            if sub is not None:
                sub.undeclare()
            self._rx_stop.set()
            self._rx.join(timeout)
            with self._cv:
                self._q.append(_STOP)  # after everything taken, never dropped
                self._cv.notify()
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("recorder writer thread did not finish within %.0f s", timeout)
            else:
                self.writer.close()
            if self.view is not None:
                self.view.close()
        return self.counters()


@functools.lru_cache(maxsize=1024)
def _parsed(key_expr: str) -> tuple[str, str, str] | None:
    """(vehicle, topic, message type) of a skyloop key, None if it is not one (a run
    has a few keys: cached)."""
    try:
        vehicle, topic = parse_key(key_expr)
        return vehicle, topic, msgtype(topic)
    except (ValueError, KeyError):
        return None


def _episode_event(key_expr: str, data: bytes) -> tuple[str, int, int] | None:
    """(vehicle, START/END, episode) if this is an episode event that decodes, else None."""
    parsed = _parsed(key_expr)
    if parsed is None or parsed[1] != keys.EPISODE:
        return None
    vehicle = parsed[0]
    try:
        msg = decode(parsed[2], data)
        event, episode = int(msg.event), int(msg.episode)
    except Exception:  # noqa: BLE001 - not an event; _write counts what is wrong
        return None
    return (vehicle, event, episode) if event in (START, END) else None


#: step topics whose messages name their episode
_NAMES_EPISODE = frozenset((keys.OBSERVATION, keys.CLOCK, keys.STEP_RECORD))


def _episode_of(key_expr: str, data: bytes) -> int | None:
    """The episode a step message names (observation, clock, step record), None for a
    message that names none or does not decode. Perception's observation comes on its own
    link and can overtake the sim's START of its episode: this places it."""
    parsed = _parsed(key_expr)
    if parsed is None or parsed[1] not in _NAMES_EPISODE:
        return None
    try:
        return int(decode(parsed[2], data).episode)
    except Exception:  # noqa: BLE001 - _write counts what is wrong
        return None


_STEP_TOPICS = frozenset((keys.CLOCK, keys.ODOM, keys.TRUTH, keys.LIDAR_POINTS,
                          keys.OBSERVATION, keys.CMD_VEL, keys.STEP_RECORD))


def _step_topic(key_expr: str) -> tuple[str | None, bool]:
    """(vehicle, whether the topic carries an episode's steps) of a key, (None, False)
    for what does not parse."""
    parsed = _parsed(key_expr)
    if parsed is None:
        return None, False
    return parsed[0], parsed[1] in _STEP_TOPICS


def run_record(out_dir: str | Path, session_config: SessionConfig | None = None,
               stop_event: threading.Event | None = None, *, vehicle: str | None = None,
               run_name: str | None = None, compression: str = "zstd",
               queue_size: int = 512, ready: threading.Event | None = None,
               split_episodes: int = 0, split_minutes: float = 0.0, ros_view: bool = True,
               scenario: str | None = None) -> RecordResult:
    """Record until ``stop_event`` is set (or Ctrl-C); return the run directory and
    counters. ``ready`` is set once the subscriber is declared. ``ros_view``: add the
    log's 3D view (:mod:`bus.ros.view`, geometry from :class:`bus.ros.scene.SitlScene`);
    ``scenario``: the one the run flies, whose world the view's worker builds first (a
    loaded machine can take longer than a short run to build the default one and then
    this one: seen in CI, a 3-episode run's log without its world)."""
    stop = stop_event if stop_event is not None else threading.Event()
    session = open_session(session_config)
    try:
        writer = EpisodeLogWriter(out_dir, run_name, compression=compression,
                                  metadata={"vehicle": vehicle or "*", **TIME_METADATA},
                                  split_episodes=split_episodes,
                                  split_minutes=split_minutes)
        view = None
        if ros_view:
            from bus.ros.scene import SitlScene, WorldWorker
            view = RosView(SitlScene(),
                           worlds=WorldWorker(prebuilt=(scenario,) if scenario else ()))
        recorder = Recorder(session, writer, vehicle, queue_size=queue_size, view=view)
        token = session.liveliness().declare_token(  # what the launcher waits on
            keys.ready_key(vehicle or keys.ANY_VEHICLE, "record"))
        log.info("recording %s into %s", recorder.key_expr, writer.path)
        if ready is not None:
            ready.set()
        try:
            while not stop.is_set():  # not stop.wait(): a signal handler may set it
                time.sleep(0.1)  # in this thread (Event.set in Event.wait: deadlock)
        except KeyboardInterrupt:
            pass
        counters = recorder.stop()
        token.undeclare()
    finally:
        session.close()
    return RecordResult(writer.dir, counters)

