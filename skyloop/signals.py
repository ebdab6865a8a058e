"""SIGTERM as Ctrl-C for the ``skyloop`` commands: ``docker stop`` and systemd send
SIGTERM; raising :class:`Stopped` (a ``KeyboardInterrupt``) in the main thread runs the
same clean-up paths as Ctrl-C, and ``skyloop.cli.main`` exits 128 + the signal (143)."""

from __future__ import annotations

import signal
from typing import Any


class Stopped(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C's ``KeyboardInterrupt``."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _raise_stopped(signum: int, frame: Any) -> None:
    raise Stopped(signum)


def stop_on_sigterm() -> None:
    """From now on SIGTERM raises :class:`Stopped` in the main thread."""
    signal.signal(signal.SIGTERM, _raise_stopped)
