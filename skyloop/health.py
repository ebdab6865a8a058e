"""``skyloop health``: is this node up? A container health check (``docker/compose.yaml``
runs it as each service's ``healthcheck``), usable from a shell as well.

Checks, each asked for by a flag, all of which must pass (exit 0; else 1 and a line
naming the first that failed):

- ``--router [ENDPOINT]``: the Zenoh router accepts TCP connections (default endpoint:
  the first of ``$SKYLOOP_ZENOH_CONNECT``). For a ``tls/`` endpoint this is the TCP
  handshake only.
- ``--session``: this network namespace (the container) holds an established TCP
  connection to the router's port: the node's own Zenoh session is connected. Read from
  ``/proc/net/tcp*``, before this command opens anything itself.
- ``--udp PORT``: a UDP socket is bound to PORT here (the bridge's MAVLink links).
- ``--ready NODE``: the node's readiness token ``skyloop/<vehicle>/ready/<NODE>`` is
  on the bus (``bus.node.Bus.declare_ready``: the policy holds it once it flies in
  OFFBOARD, the recorder once it subscribed), asked through a Zenoh session opened from
  the same ``SKYLOOP_ZENOH_*`` / ``ZENOH_CONFIG`` environment as the node's.
- ``--publishing TOPIC``: a message on ``skyloop/<vehicle>/<TOPIC>`` arrives within the
  timeout (the sim publishes ``status`` from its ground phase on: the vehicle is there
  and the bridge can send its heartbeat).
"""

from __future__ import annotations

import os
import socket
import sys
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from policy.training.settings import ConfigError
from skyloop.cli.settings_base import Repeated, VehicleFlag, bare_flag, positive

ESTABLISHED, LISTEN = "01", "0A"


def endpoint_address(endpoint: str) -> tuple[str, int]:
    """``(host, port)`` of a Zenoh endpoint such as ``tcp/router:7447``,
    ``tls/[::1]:7447#iface=eth0`` or ``tcp/10.0.0.2:7447?config``."""
    _, sep, rest = endpoint.strip().partition("/")
    if not sep or not rest:
        raise ValueError(f"not a Zenoh endpoint: {endpoint!r} (expected e.g. tcp/router:7447)")
    rest = rest.split("?", 1)[0].split("#", 1)[0]
    host, sep, port = rest.rpartition(":")
    if not sep or not port.isdigit():
        raise ValueError(f"no port in Zenoh endpoint {endpoint!r}")
    return host.strip("[]"), int(port)


def default_router() -> str | None:
    value = os.environ.get("SKYLOOP_ZENOH_CONNECT", "")
    return next((e.strip() for e in value.split(",") if e.strip()), None)


def _sockets(kinds: Iterable[str], proc: Path = Path("/proc/net")) -> list[tuple[int, int, str]]:
    """``(local port, remote port, state)`` of every socket in ``/proc/net/<kind>``."""
    out = []
    for kind in kinds:
        try:
            lines = (proc / kind).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            if len(f) > 3:
                out.append((int(f[1].rsplit(":", 1)[1], 16), int(f[2].rsplit(":", 1)[1], 16),
                            f[3]))
    return out


def check_router(endpoint: str, timeout: float) -> str | None:
    host, port = endpoint_address(endpoint)
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return None
    except OSError as err:
        return f"router {endpoint} not reachable ({err})"


def check_session(endpoint: str, proc: Path = Path("/proc/net")) -> str | None:
    _, port = endpoint_address(endpoint)
    if any(r == port and st == ESTABLISHED for _, r, st in _sockets(("tcp", "tcp6"), proc)):
        return None
    return f"no Zenoh session to the router (no TCP connection to port {port})"


def check_udp(port: int, proc: Path = Path("/proc/net")) -> str | None:
    if any(local == port for local, _, _ in _sockets(("udp", "udp6"), proc)):
        return None
    return f"nothing bound to UDP {port}"


def _session(timeout: float):
    from dataclasses import replace

    from bus.session import SessionConfig, open_session

    cfg = SessionConfig.from_env()
    if cfg.mode == "client":  # never wait for the router longer than the check may
        cfg = replace(cfg, connect_timeout_s=timeout)
    return open_session(cfg)


def check_ready(node: str, vehicle: str, timeout: float) -> str | None:
    import zenoh

    from bus.keys import ready_key

    key = ready_key(vehicle, node)
    try:
        session = _session(timeout)
    except zenoh.ZError as err:
        return f"no Zenoh session for the readiness query ({err})"
    try:
        for reply in session.liveliness().get(key, timeout=timeout):
            if reply.ok is not None:
                return None
        return f"{node} not ready (no token {key})"
    finally:
        session.close()


def check_publishing(topic: str, vehicle: str, timeout: float) -> str | None:
    import threading

    import zenoh

    from bus.keys import key

    expr = key(vehicle, topic)
    try:
        session = _session(timeout)
    except zenoh.ZError as err:
        return f"no Zenoh session to listen for {expr} ({err})"
    seen = threading.Event()
    try:
        sub = session.declare_subscriber(expr, lambda _sample: seen.set())
        got = seen.wait(timeout)
        sub.undeclare()
        return None if got else f"nothing on {expr} within {timeout:g} s"
    finally:
        session.close()


def run_checks(args: HealthCommand) -> tuple[list[str], str | None]:
    """``(passed, failure)``: the checks that passed, then the first failure or None."""
    passed: list[str] = []
    router = args.router if args.router not in (None, "") else default_router()
    if (args.router is not None or args.session) and router is None:
        return passed, "no router endpoint (give --router ENDPOINT or $SKYLOOP_ZENOH_CONNECT)"
    checks = []
    if args.session:  # first: before this command opens a connection of its own
        checks.append((f"session to {router}", lambda: check_session(router)))
    for port in args.udp:
        checks.append((f"udp {port}", lambda p=port: check_udp(p)))
    if args.router is not None:
        checks.append((f"router {router}", lambda: check_router(router, args.timeout)))
    for node in args.ready:
        checks.append((f"{node} ready", lambda n=node: check_ready(n, args.vehicle,
                                                                   args.timeout)))
    for topic in args.publishing:
        checks.append((f"{topic} published", lambda t=topic: check_publishing(
            t, args.vehicle, args.timeout)))
    for name, check in checks:
        failure = check()
        if failure is not None:
            return passed, failure
        passed.append(name)
    return passed, None


def cmd_health(args: HealthCommand) -> int:
    t0 = time.monotonic()
    passed, failure = run_checks(args)
    ms = (time.monotonic() - t0) * 1000
    if failure is not None:
        print(f"unhealthy: {failure}", file=sys.stderr)
        return 1
    print(f"healthy: {', '.join(passed)} ({ms:.0f} ms)")
    return 0


HELP = ("is this node up: router reachable, session connected, ports bound, readiness "
        "token, topic published (a container health check; exit 0 or 1)")


@dataclass(kw_only=True)
class HealthCommand(VehicleFlag):
    """``skyloop health`` (``python -m skyloop.health``): the checks to run, generated into
    options with tyro (``skyloop.cli.dataclass_cli.parse``); ``--vehicle`` is the vehicle of
    ``--ready`` and ``--publishing``."""

    router: Annotated[str | None, tyro.conf.arg(
        metavar="[ENDPOINT]", help_behavior_hint="(default: no router check; a bare "
        "--router: the first of $SKYLOOP_ZENOH_CONNECT)")] = None
    """the Zenoh router accepts connections"""
    session: bool = False
    """this container holds a TCP connection to the router's port"""
    udp: Annotated[tuple[int, ...], Repeated, tyro.conf.arg(metavar="PORT")] = ()
    """a UDP socket is bound to PORT here"""
    ready: Annotated[tuple[str, ...], Repeated, tyro.conf.arg(metavar="NODE")] = ()
    """the node's readiness token is on the bus"""
    publishing: Annotated[tuple[str, ...], Repeated, tyro.conf.arg(metavar="TOPIC")] = ()
    """a message on skyloop/<vehicle>/TOPIC arrives"""
    timeout: Annotated[float, tyro.conf.arg(metavar="S")] = 3.0
    """seconds each network check may take"""

    def validate(self) -> None:
        super().validate()
        positive(self, "timeout")
        for udp in self.udp:
            if not 1 <= udp <= 65535:
                raise ConfigError("udp", f"must be a UDP port (1..65535), got {udp}")
        if self.router is None and not (self.session or self.udp or self.ready
                                        or self.publishing):
            raise ValueError("nothing to check: give --router, --session, --udp, --ready or "
                             "--publishing")


def parse_health(argv: Sequence[str], prog: str = "skyloop health") -> HealthCommand:
    """The checks asked for; a bare ``--router`` is ``--router ""`` (the default
    endpoint). Exits 2 with one line on a bad command line."""
    from skyloop.cli.dataclass_cli import parse

    return parse(HealthCommand, bare_flag(list(argv), "--router", ""), prog=prog,
                 description=HELP)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m skyloop.health`` and ``skyloop health``: the same command without the
    rest of the CLI's imports (a health check runs every few seconds)."""
    return cmd_health(parse_health(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    from skyloop.signals import quiet_broken_pipe

    sys.exit(quiet_broken_pipe(main))
