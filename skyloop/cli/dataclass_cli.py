"""Command lines generated from config dataclasses with tyro: one default per setting
(the dataclass field's), ``--help`` with choices and defaults, and a bad value refused
before anything starts with one line naming the flag, as argparse does
(``skyloop train: error: argument --episodes: must be at least 1, got -1``), exit 2.

tyro draws its errors as boxes of several lines; ``parse`` turns the usual ones (a bad
value, an unknown choice, a missing or unknown flag) into argparse's one line through
tyro's parse-error hook, and a ``ValueError`` the dataclass raises on construction
(``__post_init__``) into the same line. The hook is tyro's private, experimental API
(``tyro._errors``, tyro 1.0): should it change, errors fall back to tyro's own boxes,
still exit 2, and tests/stack/test_cli_generated.py fails.
"""

from __future__ import annotations

import contextlib
import re
import sys
from collections.abc import Sequence
from typing import Any, NoReturn, TypeVar

import tyro

T = TypeVar("T")
_FLAG_FIRST = re.compile(r"--[a-z0-9][a-z0-9-]*: ")

__all__ = ["UsageError", "parse"]


class UsageError(Exception):
    """A command line that cannot run; the message is argparse's one line."""


def _flags(argument: Any) -> str:
    """An argument's flags as argparse names them: ``--episodes``; a positional one by
    its metavar (``LOG``)."""
    names = argument.lowered.name_or_flags
    metavar = getattr(argument.lowered, "metavar", None)
    if names and not names[0].startswith("-") and isinstance(metavar, str) and metavar:
        return metavar
    return "/".join(names)


def _value_error(message: str) -> str:
    """A dataclass's ``ValueError`` message as argparse says it: ``--flag: problem``
    (``policy.training.settings.ConfigError``) becomes ``argument --flag: problem``."""
    return f"argument {message}" if _FLAG_FIRST.match(message) else message


def _first_line(message: str) -> str:
    """tyro's message for a value no member of a union takes (``int | None``: "no type
    matching ... Got errors: - <class 'NoneType'>: ... - <class 'int'>: invalid literal
    ...") as one line: what the types other than None said."""
    if "\n" not in message:
        return message
    said = [re.sub(r"^- <class '[^']*'>: ", "", line.strip()) for line in message.splitlines()
            if line.strip().startswith("- ") and "NoneType" not in line]
    return "; ".join(said) if said else " ".join(message.split())


def _one_line(event: Any) -> None:
    """The parse-error hook: raise ``UsageError`` with argparse's line for the events
    it knows; return (tyro's own box) for the others."""
    from tyro import _errors as e

    try:
        if isinstance(event, e.InstantiationFailure) and event.argument is None:
            raise UsageError(_value_error(event.message))  # the dataclass refused a value
        if isinstance(event, e.InstantiationFailure):  # a value of the wrong type
            message = _first_line(event.message)
        elif isinstance(event, e.InvalidChoice):
            # tyro's choices come unordered, and an optional one (``Literal[...] | None``)
            # lists None, which no one types
            choices = ", ".join(repr(c) for c in sorted(
                str(c) for c in event.choices if c not in (None, "None")))
            message = f"invalid choice: {event.value!r} (choose from {choices})"
        elif isinstance(event, e.BadValue):
            message = ("expected a value" if event.offending_value is None
                       else f"unexpected value {event.offending_value!r}")
        elif isinstance(event, e.MissingArgs):
            flags = ", ".join(_flags(a.arg) for a in event.missing_arguments)
            raise UsageError(f"the following arguments are required: {flags}")
        elif isinstance(event, e.UnrecognizedArgs):
            raise UsageError(f"unrecognized arguments: {' '.join(event.tokens)}")
        else:
            return
        raise UsageError(f"argument {_flags(event.argument)}: {message}")
    except AttributeError:  # the private payloads changed: tyro's box instead
        return


def _hook() -> contextlib.AbstractContextManager:
    errors = getattr(tyro, "_errors", None)
    on_parse_error = getattr(errors, "on_parse_error", None)
    return contextlib.nullcontext() if on_parse_error is None else on_parse_error(_one_line)


def _fail(prog: str, message: str) -> NoReturn:
    print(f"{prog}: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def parse(cls: type[T], argv: Sequence[str], prog: str, description: str) -> T:
    """``cls`` from ``argv`` (tyro; booleans that default to False are plain flags,
    ``--sync``). ``--help`` prints and exits 0; a bad command line prints argparse's
    one line naming the flag and exits 2 (``SystemExit``). A ``ValueError`` the dataclass
    raises whose message starts ``--flag: `` (``policy.training.settings.ConfigError``) prints as
    argparse's ``argument --flag: ...``."""
    try:
        with _hook():
            return tyro.cli(cls, args=list(argv), prog=prog, description=description,
                            config=(tyro.conf.FlagCreatePairsOff,))
    except UsageError as exc:
        _fail(prog, str(exc))
    except ValueError as exc:  # the dataclass refused a value, the hook did not see it
        _fail(prog, _value_error(str(exc)))
