"""Helpers shared by the loopback integration tests (Zenoh and MAVLink on 127.0.0.1)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from typing import Any

from skyloop.launcher import free_port
from skyloop.signals import block_until_started

__all__ = ["alive", "exit_status", "free_port", "interrupt", "session_members",
           "sigint_default", "started_blocked", "up_args", "wait_for"]


def sigint_default() -> None:
    """``preexec_fn`` for a child the test will Ctrl-C: SIGINT as at an interactive shell
    (a test run started in the background inherits SIGINT ignored, and a Python started
    so never raises KeyboardInterrupt)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def started_blocked() -> None:
    """``preexec_fn`` for a ``python -m skyloop`` child the test will signal at any moment,
    as ``skyloop up`` starts its nodes: SIGINT as at an interactive shell, and both stop
    signals held until skyloop's first line (``skyloop.signals.block_until_started``)."""
    sigint_default()
    block_until_started()


def up_args(*extra: str) -> list[str]:
    """``skyloop up`` on free loopback ports (Zenoh hub, MAVLink links) with ``extra``."""
    udp = [free_port(socket.SOCK_DGRAM) for _ in range(4)]
    return [sys.executable, "-m", "skyloop", "up", "--hub", f"tcp/127.0.0.1:{free_port()}",
            "--api-port", str(udp[0]), "--api-local-port", str(udp[1]),
            "--gcs-port", str(udp[2]), "--gcs-local-port", str(udp[3]), *extra]


def _stat(pid: int) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after the name (state first), None if gone."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].decode().split()
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return None


def alive(pid: int) -> bool:
    """Whether process ``pid`` runs: not gone, not a zombie (exited, not reaped yet)."""
    fields = _stat(pid)
    return fields is not None and fields[0] != "Z"


def exit_status(pid: int) -> int | None:
    """The exit code of an exited, not yet reaped process (a zombie of another parent),
    as ``Popen.returncode`` gives it (``-N``: killed by signal N); None if not a zombie."""
    fields = _stat(pid)
    if fields is None or fields[0] != "Z":
        return None
    status = int(fields[49])  # field 52, exit_code: as waitpid(2) reports it
    return -(status & 0x7F) if status & 0x7F else status >> 8


def session_members(sid: int) -> list[int]:
    """Live processes (zombies aside) of session ``sid`` (a child started with
    ``start_new_session``: its pid), from ``/proc``."""
    out = []
    for name in os.listdir("/proc"):
        if name.isdigit() and (fields := _stat(int(name))) is not None \
                and fields[0] != "Z" and int(fields[3]) == sid:
            out.append(int(name))
    return out


def wait_for(cond, timeout: float = 10.0, what: str = "condition", poll: float = 0.005) -> None:
    """Poll ``cond()`` until true; fail the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(poll)


def vehicle_messages(conn: Any, seconds: float = 0.05, system: int = 1) -> Iterator[Any]:
    """The MAVLink messages from ``system`` that reach a pymavlink ``conn`` within ``seconds``."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        msg = conn.recv_match(blocking=True, timeout=0.01)
        if msg is not None and msg.get_srcSystem() == system:
            yield msg


def interrupt(proc: subprocess.Popen, timeout: float = 15.0) -> str:
    """Ctrl-C ``proc`` (e.g. ``skyloop up``, which stops its children), wait up to
    ``timeout`` s, then kill it; return what it printed (stdout piped as text)."""
    proc.send_signal(signal.SIGINT)
    try:
        out = proc.communicate(timeout=timeout)[0]
    except subprocess.TimeoutExpired:
        proc.kill()
        out = proc.communicate()[0]
    return out or ""
