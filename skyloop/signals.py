"""SIGTERM as Ctrl-C for the ``skyloop`` commands: ``docker stop`` and systemd send
SIGTERM; raising :class:`Stopped` (a ``KeyboardInterrupt``) in the main thread runs the
same clean-up paths as Ctrl-C, and ``skyloop.cli.main.main`` exits 128 + the signal (143).

Start-up: from the first line of ``python -m skyloop`` (or the ``skyloop`` script) until
a command installs its own handling (:func:`stop_on_sigterm`, or a node's stop event),
SIGINT and SIGTERM end the process at once, 128 + the signal, with one line and no
traceback (:func:`exit_at_once`). Nothing is open yet to close then, while a
``KeyboardInterrupt`` raised inside an import prints a traceback, and one raised inside
code an import runs through ``exec`` (a dataclass's methods) makes CPython 3.11 exit by
SIGINT whatever the exit code (both seen, interrupting nodes at random moments).
Commands that handle neither signal (``train``, ``eval``, ...) get Python's own
behaviour back before they run (:func:`default_signals`). Before that first line, in the
interpreter's own start-up, SIGTERM's default action would end the process (killed by
the signal, no clean-up) and SIGINT could print a traceback: a parent that starts
``python -m skyloop`` with both signals blocked (:func:`block_until_started`, as
``skyloop up`` does) has them delivered at that first line instead.

A reader that goes away (``skyloop train --help | head -3``) ends a command quietly, as
SIGPIPE ends a C program: :func:`quiet_broken_pipe`, exit 128 + SIGPIPE (141), no
traceback."""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable
from typing import Any

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Stopped(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C's ``KeyboardInterrupt``."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _raise_stopped(signum: int, frame: Any) -> None:
    raise Stopped(signum)


def stop_on_sigterm() -> None:
    """From now on SIGTERM raises :class:`Stopped` in the main thread, and SIGINT
    ``KeyboardInterrupt`` (Python's own; still ignored if the process started with it
    ignored, as a background job does)."""
    signal.signal(signal.SIGTERM, _raise_stopped)
    if signal.getsignal(signal.SIGINT) is _exit_now:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def started_as_command() -> bool:
    """Whether this interpreter was started to run the ``skyloop`` command (``python -m
    skyloop ...``, or the ``skyloop`` script), not to import skyloop as a library."""
    argv = getattr(sys, "orig_argv", [])
    if "-m" in argv[:-1]:
        return argv[argv.index("-m") + 1] == "skyloop"
    return bool(sys.argv) and os.path.basename(sys.argv[0]) == "skyloop"


def _exit_now(signum: int, frame: Any) -> None:
    os.write(2, b"terminated\n" if signum == signal.SIGTERM else b"interrupted\n")
    os._exit(128 + signum)


def exit_at_once() -> None:
    """Until a command installs its own handling: SIGINT and SIGTERM end the process at
    once, 128 + the signal (see the module docstring). A signal the process started
    with ignored stays ignored; blocked ones (:func:`block_until_started`) are unblocked,
    and one that came meanwhile ends the process now."""
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, _exit_now)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)


def block_until_started() -> None:
    """``preexec_fn`` for a ``python -m skyloop`` child: SIGINT and SIGTERM blocked until
    skyloop's first line (:func:`exit_at_once`) unblocks them, so that a signal sent in
    the interpreter's own start-up ends it as any other start-up signal does."""
    signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)


def default_signals() -> None:
    """Python's own handling back where :func:`exit_at_once` left its own: SIGINT
    raises ``KeyboardInterrupt``, SIGTERM ends the process."""
    for sig, handler in ((signal.SIGINT, signal.default_int_handler),
                         (signal.SIGTERM, signal.SIG_DFL)):
        if signal.getsignal(sig) is _exit_now:
            signal.signal(sig, handler)


def quick_exit(code: int) -> None:
    """End the process now with ``code``, after flushing the log and the standard
    streams, without the interpreter's finalization (atexit handlers, joining
    non-daemon threads, tearing down modules): for a command that has closed everything
    it opened (``skyloop.cli.main.QUICK_EXIT``). Nor can a subscriber left declared by
    mistake (zenoh-python runs them on non-daemon threads) keep the process alive."""
    import logging

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a reader gone, or closed: nothing to keep
            pass
    os._exit(code)


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


class StopFlag:
    """A stop request a signal handler may set: :meth:`set` takes no lock.

    ``threading.Event.set`` takes the event's lock; a handler runs in the main thread
    between two bytecodes, so a signal that arrives while that thread holds the lock
    (inside ``Event.wait``, or inside the handler's own ``Event.set`` when a second
    signal follows the first) deadlocks it: seen, a policy and a perception that
    outlived their SIGKILLed launcher (both got its parent-death SIGTERM). Readers poll
    :meth:`is_set` (``node.run(stop.is_set)``) or :meth:`wait`, which sleeps in short
    steps."""

    def __init__(self) -> None:
        self._set = False

    def set(self) -> None:
        self._set = True

    def is_set(self) -> bool:
        return self._set

    def wait(self, timeout: float, step: float = 0.05) -> bool:
        """Sleep until set or ``timeout`` seconds passed; whether it is set."""
        import time

        end = time.monotonic() + timeout
        while not self._set and time.monotonic() < end:
            time.sleep(min(step, max(0.0, end - time.monotonic())))
        return self._set


def stop_flag_on_signals() -> StopFlag:
    """A :class:`StopFlag` that SIGINT and SIGTERM set."""
    stop = StopFlag()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop
