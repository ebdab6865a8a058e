"""What the commands' settings dataclasses share (``skyloop.cli.stack_settings``,
``skyloop.cli.tools``, ``skyloop.health``): a base whose checks run on construction,
the range checks (a ``ConfigError`` naming the flag, which ``skyloop.cli.dataclass_cli.parse``
prints as argparse's one line), the ``--vehicle`` flag, repeatable flags and flags whose
value may be left out. Light: ``python -m skyloop.health`` imports it every few seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import tyro

from policy.training.settings import ConfigError

__all__ = ["Repeated", "Settings", "VehicleFlag", "at_least", "bare_flag",
           "minutes_or_off", "port", "positive"]

Repeated = tyro.conf.UseAppendAction  # --param A=1 --param B=2, as argparse's append


class Settings:
    """A command's settings: :meth:`validate` runs on construction; each mixin checks
    its own fields and calls ``super().validate()``."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ``ConfigError`` (naming the flag) for a value that cannot run."""


def at_least(config: object, name: str, least: int) -> None:
    """``config.name`` (an integer, or None: left out) is at least ``least``."""
    value = getattr(config, name)
    if value is not None and value < least:
        word = "0 or more" if least == 0 else f"at least {least}"
        raise ConfigError(name, f"must be {word}, got {value}")


def positive(config: object, name: str) -> None:
    """``config.name`` is a finite number above 0."""
    value = getattr(config, name)
    if not (math.isfinite(value) and value > 0.0):
        raise ConfigError(name, f"must be a finite number above 0, got {value}")


def minutes_or_off(config: object, name: str) -> None:
    """``config.name`` is 0 (off) or a finite number of minutes above 0."""
    value = getattr(config, name)
    if not (math.isfinite(value) and value >= 0):
        raise ConfigError(name, f"must be 0 (off) or more minutes, got {value:g}")


def port(config: object, name: str, least: int = 1) -> None:
    """``config.name`` is a port number (``least``..65535)."""
    value = getattr(config, name)
    if not least <= value <= 65535:
        raise ConfigError(name, f"must be a UDP port ({least}..65535), got {value}")


def bare_flag(argv: list[str], flag: str, value: str) -> list[str]:
    """``flag`` given without a value (last, or before another flag) means ``flag
    value``, as an argparse option with an optional value (``nargs="?"``) did."""
    out: list[str] = []
    for i, arg in enumerate(argv):
        out.append(arg)
        if arg == flag and (i + 1 == len(argv) or argv[i + 1].startswith("-")):
            out.append(value)
    return out


@dataclass(kw_only=True)
class VehicleFlag(Settings):
    vehicle: str = "uav1"
    """vehicle name: its topics are skyloop/<vehicle>/..."""

    def validate(self) -> None:
        super().validate()
        from bus.keys import check_vehicle

        try:
            check_vehicle(self.vehicle)
        except ValueError as err:
            raise ConfigError("vehicle", str(err)) from None
