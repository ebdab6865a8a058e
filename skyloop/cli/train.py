"""``skyloop train``: its options are generated from ``TrainConfig`` with tyro
(``skyloop.cli.dataclass_cli``), so each default lives once, in the dataclass, and
``--help`` shows it with the choices. The few options that are not the run's config
(where it goes, resuming, learning from logs) are ``TrainCommand``'s own fields.

``TrainConfig`` lives in the light ``policy.training.settings`` (``policy.training.train``
re-exports it): parsing imports no torch, so ``--help`` and a bad command line answer at
once; the trainer and the offline learner are imported only to run."""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from policy.training.settings import OFFLINE_UPDATES, ConfigError, TrainConfig
from skyloop.cli.dataclass_cli import parse

__all__ = ["TrainCommand", "main", "parse_train", "run_train"]

DESCRIPTION = ("Train TD3/DDPG with a goal reward in the in-process env (policy.training.train), "
               "or learn offline from episode logs with --from-logs (policy.logs.offline).")

RUN_HELP = "the run (policy.training.settings.TrainConfig; grid files set the same fields by name)"


@dataclass(kw_only=True)
class TrainCommand:
    """The ``skyloop train`` command line: the run's config and what to do with it."""

    config: Annotated[TrainConfig, tyro.conf.OmitArgPrefixes,
                      tyro.conf.arg(name="run", help=RUN_HELP)] = field(default_factory=TrainConfig)
    out: Path
    """run directory: CSV, TensorBoard, checkpoints (with --from-logs: actor.pt)"""
    resume: bool = False
    """continue from OUT/checkpoint.pt"""
    # the run's --reward and --seed apply to it; the other TrainConfig options do not
    from_logs: Annotated[tuple[Path, ...] | None, tyro.conf.arg(metavar="LOG [LOG ...]")] = None
    """learn offline from episode logs (MCAP files or run directories) instead"""
    updates: int = OFFLINE_UPDATES
    """with --from-logs: TD3 updates"""
    bc: bool = False
    """with --from-logs: TD3+BC instead of TD3"""
    init_actor: Path | None = None
    """with --from-logs: start from this actor file"""

    def __post_init__(self) -> None:
        if self.updates < 1:
            raise ConfigError("updates", f"must be at least 1, got {self.updates}")
        if self.from_logs is not None and not self.from_logs:
            raise ConfigError("from_logs", "expected at least one log")


def parse_train(argv: Sequence[str]) -> TrainCommand:
    """The command line after ``skyloop train``; exits 2 with one line on a bad one."""
    return parse(TrainCommand, argv, prog="skyloop train", description=DESCRIPTION)


def run_train(command: TrainCommand) -> int:
    """Train (or learn from logs), print the summary as JSON."""
    if command.from_logs is not None:
        from policy.logs.offline import train_from_logs

        summary = train_from_logs(list(command.from_logs), command.out,
                                  reward=command.config.reward, updates=command.updates,
                                  seed=command.config.seed, bc=command.bc,
                                  init_actor=command.init_actor)
        for reason, n in summary["skipped"].items():  # also in the JSON: said, not silent
            print(f"skyloop train: skipped {n} episode(s) or file(s): {reason}", file=sys.stderr)
    else:
        from policy.training.train import Trainer

        summary = Trainer(command.config, command.out).run(resume=command.resume)
    print(json.dumps(summary, indent=2))
    return 0


def main(argv: Sequence[str]) -> int:
    """``skyloop train ARGS``: parse, then run."""
    return run_train(parse_train(argv))
