"""``skyloop learner``: the actor-learner's command line, generated from
:class:`policy.nodes.learner.LearnerConfig` with tyro (``skyloop.cli.dataclass_cli``), so each
default lives once, in the dataclass, and ``--help`` shows it with the choices; the
Zenoh flags are the nodes' (``skyloop.cli.stack_settings.ZenohFlags``). The node,
:mod:`policy.nodes.learner_node`, is imported only when the command runs.

Example: two vehicles' stacks (``skyloop sim/perception/bridge/policy --vehicle uav1``
and ``uav2``, distinct MAVLink ports) and::

    skyloop learner --vehicles uav1 uav2 --algo td3 --reward abr --out runs/learner
"""

from __future__ import annotations

import json
import logging
import signal
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from policy.nodes.learner import LearnerConfig
from skyloop.cli.dataclass_cli import parse
from skyloop.cli.stack_settings import ZenohFlags

__all__ = ["HELP", "LearnerCommand", "main", "parse_learner", "run_learner"]

HELP = ("learn from live episodes on the bus, publish actor weights that "
        "'policy --weights-from-bus' nodes fly")


@dataclass(kw_only=True)
class LearnerCommand(ZenohFlags):
    """The ``skyloop learner`` command line: the learner's config, where it writes, and
    the Zenoh session."""

    config: Annotated[LearnerConfig, tyro.conf.OmitArgPrefixes, tyro.conf.arg(
        name="learner", help="the learner (policy.nodes.learner.LearnerConfig)")] = field(
        default_factory=LearnerConfig)
    out: Annotated[Path, tyro.conf.arg(metavar="DIR")]
    """run directory (checkpoint, actor.pt)"""
    no_progress: bool = False
    """no progress bar"""


def parse_learner(argv: Sequence[str]) -> LearnerCommand:
    """The command line after ``skyloop learner``; exits 2 with one line on a bad one."""
    return parse(LearnerCommand, argv, prog="skyloop learner", description=HELP)


def run_learner(args: LearnerCommand) -> int:
    from bus.node import Bus
    from bus.session import SessionConfig
    from policy.nodes.learner_node import Learner

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    bus = Bus.open(SessionConfig.from_flags(args.mode, args.connect, args.listen,
                                               args.zenoh_config))
    try:
        learner = Learner(bus, args.config, args.out,
                          emit=lambda line: print(line, flush=True))
        summary = learner.run(stop.is_set, progress=not args.no_progress)
    finally:
        bus.close()
    print(f"learner: {summary['episodes']} episodes {summary['by_vehicle']}, "
          f"{summary['updates']} updates, version {summary['version']}, skipped "
          f"{json.dumps(summary['skipped'])}; checkpoint {summary['checkpoint']}",
          file=sys.stderr, flush=True)
    return 0


def main(argv: Sequence[str]) -> int:
    """``skyloop learner ARGS``: parse, then run."""
    return run_learner(parse_learner(argv))
