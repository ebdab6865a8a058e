"""argparse value types and shared flags for the ``skyloop`` commands: a bad number is
a one-line usage error naming the flag (argparse adds it), before anything starts."""

from __future__ import annotations

import argparse
import math


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None


def positive_int(text: str) -> int:
    """An integer >= 1."""
    value = _int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def nonnegative_int(text: str) -> int:
    """An integer >= 0."""
    value = _int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text}")
    return value


def add_bus_flags(p: argparse.ArgumentParser, vehicle: bool = True) -> None:
    """The Zenoh flags every node takes (``SessionConfig.from_flags``), ``--vehicle``
    (a node of one vehicle) and ``-v``."""
    if vehicle:
        p.add_argument("--vehicle", default="uav1", help="vehicle name (default: uav1)")
    p.add_argument("--mode", choices=("peer", "client"), default=None,
                   help="Zenoh mode (default: $SKYLOOP_ZENOH_MODE or peer)")
    p.add_argument("--connect", default=None, help="Zenoh endpoints, comma-separated")
    p.add_argument("--listen", default=None, help="Zenoh endpoints to listen on")
    p.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="a Zenoh configuration file: TLS certificates, access control "
                        "(default: $ZENOH_CONFIG; `skyloop certs` writes them)")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
