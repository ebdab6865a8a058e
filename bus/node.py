"""The :class:`Bus`: typed publishers and subscribers over one Zenoh session.

Publishers encode with :func:`bus.messages.encode` and use the topic table's congestion
control (``BLOCK`` for every topic by default: point clouds are lost silently under
``DROP``, and lockstep and the log need every message). Subscribers decode inside the
Zenoh callback; a payload that does not decode, and an exception raised by the user
callback, are counted and logged (rate-limited), never raised into Zenoh's thread.

Callbacks run on Zenoh's threads: keep them short and never block in them. For a
consumer that waits, use :meth:`Bus.inbox` (a bounded queue; a full queue drops the
oldest message and counts it).

Request/reply (the commander's requests): :meth:`Bus.queryable` declares a
:class:`Queryable` whose queries wait in Zenoh's FIFO channel until the owner takes them
(:meth:`Queryable.take`, non-blocking) and answers each when it likes
(:meth:`Request.reply`) -- no user code runs in Zenoh's threads; :meth:`Bus.query` sends
one request and waits (bounded) for the decoded reply, ``None`` if nobody answered.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from bus.keys import key, ready_key, topic_info
from bus.messages import decode, encode
from bus.session import SessionConfig, open_session

log = logging.getLogger("skyloop.bus")

#: Payloads at least this large always go out with ``CongestionControl.BLOCK``.
LARGE_PAYLOAD = 64 * 1024


class RateLimitedLog:
    """Log at most one line per ``interval_s``, reporting how many were suppressed."""

    def __init__(self, logger: logging.Logger, interval_s: float = 5.0) -> None:
        self.logger, self.interval_s = logger, interval_s
        self._last = -float("inf")
        self._suppressed = 0
        self._lock = threading.Lock()

    def __call__(self, level: int, msg: str, *args: object, exc_info: bool = False) -> None:
        now = time.monotonic()
        with self._lock:
            if now - self._last < self.interval_s:
                self._suppressed += 1
                return
            suppressed, self._suppressed, self._last = self._suppressed, 0, now
        if suppressed:
            msg += f" ({suppressed} similar suppressed)"
        self.logger.log(level, msg, *args, exc_info=exc_info)


class Publisher:
    """Publisher of one topic of one vehicle; :meth:`put` takes a message object."""

    def __init__(self, session: zenoh.Session, topic: str, vehicle: str, *,
                 congestion: str | None = None, express: bool | None = None,
                 priority: zenoh.Priority | None = None) -> None:
        info = topic_info(topic)
        self.topic, self.vehicle, self.msgtype = topic, vehicle, info.msgtype
        self.key = key(vehicle, topic)
        self._session = session
        self._block = (congestion or info.congestion) == "block"
        cc = zenoh.CongestionControl.BLOCK if self._block else zenoh.CongestionControl.DROP
        kwargs: dict[str, Any] = {"congestion_control": cc,
                                  "express": info.express if express is None else express}
        if priority is not None:
            kwargs["priority"] = priority
        self._pub: zenoh.Publisher | None = session.declare_publisher(self.key, **kwargs)
        self.sent = 0
        self.sent_bytes = 0

    def put(self, msg: Any) -> int:
        """Encode and publish ``msg`` (must be of this topic's type); return its size."""
        if getattr(msg, "__msgtype__", None) != self.msgtype:
            raise TypeError(f"{self.key} carries {self.msgtype}, got "
                            f"{getattr(msg, '__msgtype__', type(msg).__name__)}")
        return self.put_bytes(encode(msg))

    def put_bytes(self, data: bytes) -> int:
        """Publish an already encoded payload (replay, tests); return its size."""
        if self._pub is None:
            raise RuntimeError(f"publisher {self.key} is closed")
        if not self._block and len(data) >= LARGE_PAYLOAD:
            self._session.put(self.key, data, congestion_control=zenoh.CongestionControl.BLOCK)
        else:
            self._pub.put(data)
        self.sent += 1
        self.sent_bytes += len(data)
        return len(data)

    @property
    def matched(self) -> bool:
        """Whether some subscriber currently matches this publisher's key."""
        return self._pub is not None and bool(self._pub.matching_status.matching)

    def wait_matched(self, timeout: float = 5.0) -> bool:
        """Wait until a subscriber matches (True) or ``timeout`` seconds pass (False)."""
        deadline = time.monotonic() + timeout
        while not self.matched:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.005)
        return True

    def close(self) -> None:
        """Undeclare (idempotent)."""
        pub, self._pub = self._pub, None
        if pub is not None:
            pub.undeclare()


class Subscription:
    """Subscriber of one topic (one vehicle, or ``'*'`` for all) that decodes in the
    Zenoh callback and calls ``callback(msg)`` (``callback(vehicle, msg)`` with
    ``with_vehicle``). Counters: ``received``, ``decode_errors``, ``callback_errors``."""

    def __init__(self, session: zenoh.Session, topic: str, vehicle: str,
                 callback: Callable[..., Any], *, with_vehicle: bool = False,
                 log_interval_s: float = 5.0) -> None:
        self.topic, self.vehicle = topic, vehicle
        self.msgtype = topic_info(topic).msgtype
        self.key = key(vehicle, topic, wildcard=True)
        self._callback, self._with_vehicle = callback, with_vehicle
        self._lock = threading.Lock()
        self.received = self.decode_errors = self.callback_errors = 0
        self._log = RateLimitedLog(log, log_interval_s)
        self._sub: zenoh.Subscriber | None = session.declare_subscriber(self.key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            msg = decode(self.msgtype, sample.payload.to_bytes())
        except Exception as err:  # noqa: BLE001 - never raise into Zenoh
            with self._lock:
                self.decode_errors += 1
            self._log(logging.WARNING, "%s: payload does not decode as %s: %s",
                      str(sample.key_expr), self.msgtype, err)
            return
        with self._lock:
            self.received += 1
        try:
            if self._with_vehicle:
                self._callback(str(sample.key_expr).split("/", 2)[1], msg)
            else:
                self._callback(msg)
        except Exception:  # noqa: BLE001 - never raise into Zenoh
            with self._lock:
                self.callback_errors += 1
            self._log(logging.ERROR, "%s: callback raised", self.key, exc_info=True)

    def counters(self) -> dict[str, int]:
        """Snapshot of the counters."""
        with self._lock:
            return {"received": self.received, "decode_errors": self.decode_errors,
                    "callback_errors": self.callback_errors}

    def close(self) -> None:
        """Undeclare (idempotent; waits for a running callback to finish)."""
        sub, self._sub = self._sub, None
        if sub is not None:
            sub.undeclare()


def inbox_drops(inboxes) -> dict[str, int]:
    """What bounded inboxes dropped, per inbox (``dropped_<topic>``) and in total
    (``dropped``): the counters a node prints at exit (the inboxes count as they drop)."""
    each = {f"dropped_{i.subscription.topic}": i.dropped for i in inboxes}
    return {"dropped": sum(each.values()), **each}


class Inbox:
    """A subscription feeding a bounded queue, for consumers that wait (:meth:`get`).

    Items are messages (``(vehicle, msg)`` with ``with_vehicle``). When the queue is full
    the oldest item is dropped and counted in ``dropped``.
    """

    def __init__(self, session: zenoh.Session, topic: str, vehicle: str, maxsize: int = 64,
                 *, with_vehicle: bool = False) -> None:
        self._q: queue.Queue[Any] = queue.Queue(maxsize=maxsize)
        self.dropped = 0
        self.subscription = Subscription(session, topic, vehicle, self._push,
                                         with_vehicle=with_vehicle)

    def _push(self, *item: Any) -> None:
        value = item if len(item) > 1 else item[0]
        while True:
            try:
                self._q.put_nowait(value)
                return
            except queue.Full:
                try:
                    self._q.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass

    def get(self, timeout: float | None = None) -> Any:
        """Next item; ``TimeoutError`` after ``timeout`` seconds (``None``: wait forever)."""
        try:
            return self._q.get(timeout=timeout)
        except queue.Empty:
            raise TimeoutError(f"nothing on {self.subscription.key} within {timeout} s") from None

    def get_nowait(self) -> Any | None:
        """Next item, or ``None`` if the queue is empty."""
        try:
            return self._q.get_nowait()
        except queue.Empty:
            return None

    def __len__(self) -> int:
        return self._q.qsize()

    def counters(self) -> dict[str, int]:
        """The subscription's counters plus ``dropped``."""
        return {**self.subscription.counters(), "dropped": self.dropped}

    def close(self) -> None:
        """Undeclare (idempotent)."""
        self.subscription.close()


class Request:
    """One query taken from a :class:`Queryable`: the decoded ``msg`` and its reply."""

    def __init__(self, query: Any, msg: Any) -> None:
        self._query, self.msg = query, msg

    def reply(self, msg: Any) -> None:
        """Answer with ``msg`` (any type of the type store); a failure is logged."""
        try:
            self._query.reply(self._query.key_expr, encode(msg))
        except Exception:  # noqa: BLE001 - the querier gave up or the session is closing
            log.warning("reply to %s failed", self._query.key_expr, exc_info=True)
        self._query = None  # dropping the query finalises it


class Queryable:
    """Queries on one topic of one vehicle, queued until :meth:`take` (see module doc).
    Counters: ``received``, ``decode_errors`` (answered with an error reply)."""

    def __init__(self, session: zenoh.Session, topic: str, vehicle: str) -> None:
        self.topic, self.msgtype = topic, topic_info(topic).msgtype
        self.key = key(vehicle, topic)
        self.received = self.decode_errors = 0
        self._log = RateLimitedLog(log)
        self._q: Any = session.declare_queryable(self.key)

    def take(self) -> list[Request]:
        """Every query waiting now, decoded (never blocks)."""
        out: list[Request] = []
        while self._q is not None and (query := self._q.try_recv()) is not None:
            try:
                payload = query.payload
                msg = decode(self.msgtype, payload.to_bytes() if payload is not None else b"")
            except Exception as err:  # noqa: BLE001 - a bad request is answered, not raised
                self.decode_errors += 1
                self._log(logging.WARNING, "%s: request does not decode as %s: %s",
                          self.key, self.msgtype, err)
                try:
                    query.reply_err(f"request does not decode as {self.msgtype}".encode())
                except Exception:  # noqa: BLE001
                    pass
                continue
            self.received += 1
            out.append(Request(query, msg))
        return out

    def counters(self) -> dict[str, int]:
        return {"received": self.received, "decode_errors": self.decode_errors}

    def close(self) -> None:
        """Undeclare (idempotent)."""
        q, self._q = self._q, None
        if q is not None:
            q.undeclare()


class ReadyToken:
    """A node's readiness: a Zenoh liveliness token, gone on ``close`` (or death)."""

    def __init__(self, session: zenoh.Session, vehicle: str, node: str) -> None:
        self.key = ready_key(vehicle, node)
        self._token: Any = session.liveliness().declare_token(self.key)

    def close(self) -> None:
        token, self._token = self._token, None
        if token is not None:
            token.undeclare()


class ReadyWatch:
    """Calls ``callback(node, alive)`` as nodes of ``vehicle`` become ready (alive=True)
    or go away (False); tokens declared before the watch started are reported too."""

    def __init__(self, session: zenoh.Session, vehicle: str,
                 callback: Callable[[str, bool], None]) -> None:
        self.key = ready_key(vehicle)
        self._callback = callback
        self._sub: Any = session.liveliness().declare_subscriber(self.key, self._on_sample,
                                                                 history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        node = str(sample.key_expr).rsplit("/", 1)[-1]
        try:
            self._callback(node, sample.kind == zenoh.SampleKind.PUT)
        except Exception:  # noqa: BLE001 - a callback error must not kill Zenoh's thread
            log.exception("readiness callback failed for %s", node)

    def close(self) -> None:
        sub, self._sub = self._sub, None
        if sub is not None:
            sub.undeclare()


class Bus:
    """Typed access to the ``skyloop/<vehicle>/<topic>`` keys over one session.

    ``Bus.open(cfg)`` opens (and owns) a session; ``Bus(session)`` wraps one the caller
    owns. :meth:`close` undeclares every entity, then closes an owned session.
    """

    def __init__(self, session: zenoh.Session, *, owns_session: bool = False) -> None:
        self.session = session
        self._owns = owns_session
        self._entities: list[Any] = []  # publishers, subscriptions, tokens ...
        self._closed = False

    @classmethod
    def open(cls, cfg: SessionConfig | None = None) -> Bus:
        """Open a session with :func:`bus.session.open_session` (``cfg`` a
        ``SessionConfig``; ``None``: from the environment) and own it."""
        return cls(open_session(cfg), owns_session=True)

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("bus is closed")

    def _track(self, entity: Any) -> Any:
        self._entities.append(entity)
        return entity

    def publisher(self, topic: str, vehicle: str, **options: Any) -> Publisher:
        """Declare a :class:`Publisher` (``options``: congestion, express, priority)."""
        self._check_open()
        return self._track(Publisher(self.session, topic, vehicle, **options))

    def subscribe(self, topic: str, vehicle: str, callback: Callable[..., Any], *,
                  with_vehicle: bool = False) -> Subscription:
        """Declare a decoding :class:`Subscription` (``vehicle='*'`` for all vehicles)."""
        self._check_open()
        return self._track(Subscription(self.session, topic, vehicle, callback,
                                        with_vehicle=with_vehicle))

    def inbox(self, topic: str, vehicle: str, maxsize: int = 64, *,
              with_vehicle: bool = False) -> Inbox:
        """Declare an :class:`Inbox` (queue-backed subscription)."""
        self._check_open()
        return self._track(Inbox(self.session, topic, vehicle, maxsize,
                                 with_vehicle=with_vehicle))

    def declare_ready(self, vehicle: str, node: str) -> ReadyToken:
        """Tell the launcher (and anyone watching) that ``node`` of ``vehicle`` is ready:
        a liveliness token that lasts until :meth:`close` or the process dies."""
        self._check_open()
        return self._track(ReadyToken(self.session, vehicle, node))

    def watch_ready(self, vehicle: str, callback: Callable[[str, bool], None]) -> ReadyWatch:
        """Watch the readiness tokens of ``vehicle``'s nodes (:class:`ReadyWatch`)."""
        self._check_open()
        return self._track(ReadyWatch(self.session, vehicle, callback))

    def queryable(self, topic: str, vehicle: str) -> Queryable:
        """Declare a :class:`Queryable` (requests on ``topic`` of ``vehicle``)."""
        self._check_open()
        return self._track(Queryable(self.session, topic, vehicle))

    def query(self, topic: str, vehicle: str, msg: Any, reply_type: str,
              timeout: float = 1.0) -> Any | None:
        """Send ``msg`` as a query on ``topic`` and return the first reply decoded as
        ``reply_type``; ``None`` if no queryable answered within ``timeout`` seconds, or
        the answer was an error or did not decode (logged)."""
        self._check_open()
        k = key(vehicle, topic)
        if getattr(msg, "__msgtype__", None) != topic_info(topic).msgtype:
            raise TypeError(f"{k} takes {topic_info(topic).msgtype}")
        for reply in self.session.get(k, payload=encode(msg), timeout=timeout):
            if reply.ok is None:
                log.warning("%s: error reply: %s", k, reply.err.payload.to_bytes()[:200])
                return None
            try:
                return decode(reply_type, reply.ok.payload.to_bytes())
            except Exception as err:  # noqa: BLE001
                log.warning("%s: reply does not decode as %s: %s", k, reply_type, err)
                return None
        return None

    def counters(self) -> dict[str, int]:
        """Totals over every entity declared on this bus (closed ones included)."""
        total = {"published": 0, "published_bytes": 0, "received": 0, "decode_errors": 0,
                 "callback_errors": 0, "dropped": 0}
        for ent in list(self._entities):
            if isinstance(ent, Publisher):
                total["published"] += ent.sent
                total["published_bytes"] += ent.sent_bytes
            elif isinstance(ent, Queryable):
                total["received"] += ent.received
                total["decode_errors"] += ent.decode_errors
            else:
                for name, value in ent.counters().items():
                    total[name] += value
        return total

    def close(self) -> None:
        """Undeclare every subscriber and publisher, then close an owned session.

        Everything is undeclared even if Ctrl-C (``KeyboardInterrupt``) or SIGTERM lands in
        the middle: zenoh-python runs callback subscribers on non-daemon threads, so one
        left declared would keep the process alive. The interrupt is raised again after.
        """
        if self._closed:
            return
        self._closed = True
        interrupted: BaseException | None = None
        for ent in reversed(self._entities):
            try:
                ent.close()
            except Exception:  # noqa: BLE001 - keep closing the rest
                log.warning("undeclaring %s failed", getattr(ent, "key", ent), exc_info=True)
            except BaseException as exc:  # noqa: BLE001 - Ctrl-C: finish, then re-raise
                interrupted = interrupted or exc
        if self._owns:
            self.session.close()
        if interrupted is not None:
            raise interrupted

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
