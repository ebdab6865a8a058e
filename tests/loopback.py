"""Helpers shared by the loopback integration tests (Zenoh and MAVLink on 127.0.0.1)."""

from __future__ import annotations

import signal
import subprocess
import time

from skyloop.launcher import free_port

__all__ = ["free_port", "interrupt", "sigint_default", "wait_for"]


def sigint_default() -> None:
    """``preexec_fn`` for a child the test will Ctrl-C: SIGINT as at an interactive shell
    (a test run started in the background inherits SIGINT ignored, and a Python started
    so never raises KeyboardInterrupt)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def wait_for(cond, timeout: float = 10.0, what: str = "condition", poll: float = 0.005) -> None:
    """Poll ``cond()`` until true; fail the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(poll)


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
