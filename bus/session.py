"""Zenoh sessions: configuration, discovery without multicast, the Python router.

Discovery on one machine (the default): every process is a *peer* on loopback with
multicast scouting off (multicast does not cross containers and sandboxes). One
well-known *hub* endpoint, ``tcp/127.0.0.1:7447`` by default, ties them together:

1. :func:`open_session` first tries to listen on the hub. The first process to bind it
   becomes the hub (the bind is the election; the OS makes it atomic).
2. Every later process fails that bind within milliseconds, listens on an ephemeral
   loopback port (``tcp/127.0.0.1:0``) and connects to the hub.
3. Gossip scouting (on by default in peer mode) tells each newcomer, through the hub,
   the locators of the other peers, and the peers connect to each other directly, so
   data does not hop through the hub, and traffic between peers survives the hub
   process exiting (a process started after that claims the hub again).

Explicit ``listen`` / ``connect`` endpoints turn the hub logic off. Across hosts, or
when an always-on rendezvous is wanted, run a router (``zenohd``, or :func:`run_router`:
a Python session in router mode, no binary needed; ``skyloop router`` runs it) and open
every node in ``client`` mode with ``connect`` pointing at it.

Environment (:meth:`SessionConfig.from_env`): ``SKYLOOP_ZENOH_MODE`` (peer, client,
router), ``SKYLOOP_ZENOH_CONNECT`` and ``SKYLOOP_ZENOH_LISTEN`` (comma-separated
endpoints), ``SKYLOOP_ZENOH_HUB`` (the hub endpoint, e.g. for a second stack on the
same machine).

Measured (two Python processes, hub scheme, Bus encode/decode included, other core
busy): round trip p50 0.19 ms / p99 0.26 ms for a TwistStamped, 0.55 / 0.74 ms for a
28,800-point scan (345 KB). Peers started before the hub exists, or left behind when it
exits, keep retrying the hub endpoint in the background and join the next hub.

Pitfalls (``shared/notes/zenoh-python.md``): never fork after opening a session (start
children with ``spawn`` or as new programs); close explicitly, undeclaring first
(:class:`bus.node.Bus` does, built on this module's sessions).
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import zenoh

__all__ = ["HUB", "LOOPBACK_ANY", "SessionConfig", "SessionError", "open_router",
           "open_session", "run_router"]

log = logging.getLogger("skyloop.bus")

HUB = "tcp/127.0.0.1:7447"
LOOPBACK_ANY = "tcp/127.0.0.1:0"
MODES = ("peer", "client", "router")
ENV_MODE = "SKYLOOP_ZENOH_MODE"
ENV_CONNECT = "SKYLOOP_ZENOH_CONNECT"
ENV_LISTEN = "SKYLOOP_ZENOH_LISTEN"
ENV_CONFIG = "ZENOH_CONFIG"  # the variable Zenoh's own tools read
ENV_HUB = "SKYLOOP_ZENOH_HUB"


class SessionError(ValueError):
    """Zenoh could not open a session (an endpoint taken or unreachable): one line naming
    the endpoint, without the Rust source locations; ``skyloop`` prints it and exits 2."""

    def __init__(self, err: zenoh.ZError) -> None:
        said = re.sub(r" at /\S+?\.rs:\d+\.?", "", str(err)).strip()
        super().__init__(f"cannot open a Zenoh session: {said} (endpoints: --listen, "
                         f"--connect, --hub or SKYLOOP_ZENOH_*)")


def _endpoints(value: str | Sequence[str] | None) -> tuple[str, ...]:
    if value is None:
        return ()
    items = value.split(",") if isinstance(value, str) else list(value)
    return tuple(e.strip() for e in items if e and e.strip())


@dataclass(frozen=True)
class SessionConfig:
    """How to open a Zenoh session.

    ``mode``: ``peer`` (default), ``client`` (to a router) or ``router``.
    ``listen`` / ``connect``: endpoints such as ``tcp/127.0.0.1:7447``. Empty in peer
    mode means the hub scheme of the module docstring; empty ``connect`` in client
    mode means ``(hub,)``; empty ``listen`` in router mode means ``(hub,)``.
    ``multicast_scouting`` is off by default. ``connect_timeout_s`` bounds how long a
    client waits for its router at open (``None``: Zenoh's default, fail at once).
    """

    mode: str = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    hub: str = HUB
    multicast_scouting: bool = False
    connect_timeout_s: float | None = None
    extra: Mapping[str, str] = field(default_factory=dict)  # json5 path -> json5 value
    #: a standard Zenoh configuration file (JSON5) as the base: TLS certificates,
    #: authentication, access control (``skyloop certs`` writes them); its mode and
    #: endpoints give way to the fields above
    config_file: str | None = None

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        object.__setattr__(self, "listen", _endpoints(self.listen))
        object.__setattr__(self, "connect", _endpoints(self.connect))
        if self.mode == "client" and self.listen:
            raise ValueError("a client does not listen; use peer or router mode")

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None, **defaults: object) -> SessionConfig:
        """Config from ``SKYLOOP_ZENOH_*`` variables over ``defaults`` (field values)."""
        env = os.environ if env is None else env
        cfg = cls(**defaults)  # type: ignore[arg-type]
        changes: dict[str, object] = {}
        if env.get(ENV_MODE, "").strip():
            changes["mode"] = env[ENV_MODE].strip().lower()
        if env.get(ENV_CONNECT, "").strip():
            changes["connect"] = _endpoints(env[ENV_CONNECT])
        if env.get(ENV_LISTEN, "").strip():
            changes["listen"] = _endpoints(env[ENV_LISTEN])
        if env.get(ENV_HUB, "").strip():
            changes["hub"] = env[ENV_HUB].strip()
        if env.get(ENV_CONFIG, "").strip():
            changes["config_file"] = env[ENV_CONFIG].strip()
        return replace(cfg, **changes) if changes else cfg

    @classmethod
    def from_flags(cls, mode: str | None = None, connect: str | None = None,
                   listen: str | None = None, zenoh_config: str | None = None
                   ) -> SessionConfig:
        """``from_env`` with the command-line flags ``--mode/--connect/--listen/
        --zenoh-config`` (those given) winning over the environment."""
        cfg = cls.from_env()
        overrides = {k: v for k, v in (("mode", mode), ("connect", connect),
                                       ("listen", listen), ("config_file", zenoh_config))
                     if v is not None}
        return replace(cfg, **overrides) if overrides else cfg

    @property
    def uses_hub(self) -> bool:
        """True when :func:`open_session` runs the hub election (peer, no endpoints)."""
        return self.mode == "peer" and not self.listen and not self.connect

    def zenoh_config(self, listen: Sequence[str] | None = None,
                     connect: Sequence[str] | None = None) -> zenoh.Config:
        """The ``zenoh.Config`` for given endpoints (default: this config's, with the
        client and router defaults filled in; the hub election is not done here)."""
        if listen is None:
            listen = self.listen or ((self.hub,) if self.mode == "router" else ())
        if connect is None:
            connect = self.connect or ((self.hub,) if self.mode == "client" else ())
        conf = self._base_config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if self.connect_timeout_s is not None:
            conf.insert_json5("connect/timeout_ms", str(int(self.connect_timeout_s * 1000)))
        for path, value in self.extra.items():
            conf.insert_json5(path, value)
        return conf


    def _base_config(self) -> zenoh.Config:
        if self.config_file is None:
            return zenoh.Config()
        if not os.path.isfile(self.config_file):
            raise ValueError(f"Zenoh config {self.config_file} (--zenoh-config or "
                             f"{ENV_CONFIG}): no such file")
        try:
            return zenoh.Config.from_file(self.config_file)
        except Exception as exc:  # zenoh's error spans lines: keep the first
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise ValueError(f"Zenoh config {self.config_file}: {first}") from None


_sessions: list[zenoh.Session] = []  # opened in this process (for the fork warning)


_open_at_fork = 0


def _count_before_fork() -> None:  # in the parent: the child touches no session
    global _open_at_fork
    _open_at_fork = sum(not s.is_closed() for s in _sessions)


def _warn_fork_child() -> None:
    if _open_at_fork:
        log.warning("process forked with %d Zenoh session(s) open: the child cannot use "
                    "them; start children with 'spawn' or as new programs", _open_at_fork)


os.register_at_fork(before=_count_before_fork, after_in_child=_warn_fork_child)


def _open(conf: zenoh.Config) -> zenoh.Session:
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as err:
        raise SessionError(err) from None
    _sessions[:] = [s for s in _sessions if not s.is_closed()] + [session]
    return session


def open_session(cfg: SessionConfig | None = None) -> zenoh.Session:
    """Open a Zenoh session (``cfg`` default: :meth:`SessionConfig.from_env`).

    In hub mode (peer, no explicit endpoints) the session claims the hub endpoint if it
    is free, else listens on an ephemeral loopback port and connects to the hub. The
    caller closes the session (``session.close()``, after undeclaring its entities).
    """
    cfg = SessionConfig.from_env() if cfg is None else cfg
    if not cfg.uses_hub:
        return _open(cfg.zenoh_config())
    try:
        session = _open(cfg.zenoh_config(listen=[cfg.hub], connect=[]))
        log.debug("zenoh peer %s: hub on %s", session.info.zid(), cfg.hub)
        return session
    except SessionError as err:  # usually "Address already in use": someone is the hub
        log.debug("hub %s taken (%s); joining it", cfg.hub, err)
    session = _open(cfg.zenoh_config(listen=[LOOPBACK_ANY], connect=[cfg.hub]))
    log.debug("zenoh peer %s: joined hub %s", session.info.zid(), cfg.hub)
    return session


def open_router(listen: Sequence[str] | str = (HUB,),
                cfg: SessionConfig | None = None) -> zenoh.Session:
    """Open a Python session in router mode listening on ``listen``."""
    base = cfg if cfg is not None else SessionConfig(mode="router")
    return _open(replace(base, mode="router", listen=_endpoints(listen)).zenoh_config())


def run_router(listen: Sequence[str] | str = (HUB,),
               stop_event: threading.Event | None = None,
               cfg: SessionConfig | None = None) -> None:
    """Run a Zenoh router (a Python session in router mode; no ``zenohd`` needed) until
    ``stop_event`` is set or the process is interrupted."""
    session = open_router(listen, cfg)
    log.info("zenoh router %s listening on %s", session.info.zid(), list(_endpoints(listen)))
    stop = stop_event if stop_event is not None else threading.Event()
    try:
        while not stop.is_set():  # not stop.wait(): a signal handler may set it in
            time.sleep(0.1)  # this thread (Event.set inside Event.wait: deadlock)
    except KeyboardInterrupt:
        pass
    finally:
        session.close()

