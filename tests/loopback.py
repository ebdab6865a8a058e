"""Helpers shared by the loopback integration tests (Zenoh and MAVLink on 127.0.0.1)."""

from __future__ import annotations

import time

from skyloop.launcher import free_port

__all__ = ["free_port", "wait_for"]


def wait_for(cond, timeout: float = 10.0, what: str = "condition", poll: float = 0.005) -> None:
    """Poll ``cond()`` until true; fail the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(poll)
