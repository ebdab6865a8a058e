"""SIGTERM as Ctrl-C for the ``skyloop`` commands: ``docker stop`` and systemd send
SIGTERM; raising :class:`Stopped` (a ``KeyboardInterrupt``) in the main thread runs the
same clean-up paths as Ctrl-C, and ``skyloop.cli.main`` exits 128 + the signal (143).

A reader that goes away (``skyloop train --help | head -3``) ends a command quietly, as
SIGPIPE ends a C program: :func:`quiet_broken_pipe`, exit 128 + SIGPIPE (141), no
traceback."""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable
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


def quiet_broken_pipe(run: Callable[[], int]) -> int:
    """``run()``'s exit code; if its standard output's reader has gone (EPIPE), 128 +
    SIGPIPE and no traceback. Standard output is flushed here, so a broken pipe shows
    here and not as "Exception ignored" at interpreter exit, and then pointed at
    /dev/null, so that exit's own flush has nothing to write."""
    try:
        try:
            code = run()
        finally:  # --help exits (SystemExit) with the text perhaps still buffered
            sys.stdout.flush()
        return code
    except BrokenPipeError:
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
        except (OSError, ValueError):  # not a real file (captured output): nothing to do
            pass
        return 128 + signal.SIGPIPE
