"""The actor-learner's settings (``skyloop learner``), numpy and tyro only.

The node is :mod:`policy.nodes.learner_node`, the command line :mod:`skyloop.cli.learner`.
Policy nodes started with ``skyloop policy --weights-from-bus`` fly the versions it
publishes, swapped in between episodes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, ClassVar, get_args

import tyro

from policy.algorithms.rewards import GOAL_REWARDS as REWARDS  # numpy only
from policy.training.settings import Algo, ConfigError, Reward, check_at_least

ALGOS = get_args(Algo)  # the keys of policy.algorithms.agents.ALGOS (which imports torch)


@dataclass
class LearnerConfig:
    """What the learner learns from and how (see :mod:`policy.nodes.learner_node`). Each
    default here is the only one: ``skyloop learner``'s options are generated from these
    fields (``skyloop.cli.learner``, with tyro); a bad value is a ``ConfigError`` naming
    the flag, on construction."""

    vehicles: Annotated[list[str], tyro.conf.arg(metavar="NAME [NAME ...]")] = field(
        default_factory=lambda: ["*"])
    """vehicles to learn from and publish to ('*': every one)"""
    algo: Algo = "td3"
    """the agent"""
    reward: Reward = "abr"
    """goal reward that rewrites each episode (abr-method.md)"""
    seed: int = 0
    """the learner's seed (networks, exploration noise)"""
    updates_per_step: float = 1.0
    """TD3 updates per new env step"""
    warmup: Annotated[int, tyro.conf.arg(metavar="TRANSITIONS")] = 1000
    """transitions in the buffer before updates start"""
    critic_warmup: Annotated[int, tyro.conf.arg(metavar="UPDATES", help=(
        "the first updates train the critic only, so a fresh critic does not drag a "
        "trained --init-actor around"))] = 1000
    publish_every: Annotated[int, tyro.conf.arg(metavar="EPISODES")] = 1
    """consumed episodes between two publishes of the actor"""
    checkpoint_every: Annotated[int, tyro.conf.arg(metavar="EPISODES")] = 50
    """consumed episodes between two checkpoints"""
    init_actor: Annotated[str | None, tyro.conf.arg(
        metavar="shipped[:NAME]|scratch|FILE")] = "shipped"
    """the actor to start from: a shipped one (as --policy names it), a fresh one, or an
    actor file"""
    buffer_size: int = 1_000_000
    """replay buffer capacity in transitions"""
    max_episodes: int = 0
    """stop after this many episodes (0: until Ctrl-C/SIGTERM)"""
    grace_s: Annotated[float, tyro.conf.arg(name="grace", metavar="S")] = 2.0
    """how long an ended episode waits for its late observations and commands"""
    # not a flag: messages between the Zenoh callbacks and the main loop
    queue_size: tyro.conf.Suppress[int] = 100_000
    threads: int = 1
    """torch threads"""
    resume: bool = False
    """continue from OUT/checkpoint.pt"""

    # the least value of each count; a smaller one is refused on construction
    AT_LEAST: ClassVar[dict[str, int]] = {
        "publish_every": 1, "checkpoint_every": 1, "queue_size": 1, "buffer_size": 1,
        "threads": 1, "warmup": 0, "critic_warmup": 0, "max_episodes": 0}

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise ``ConfigError`` (a ``ValueError`` naming the flag) for a bad value; runs
        on construction, and again by the learner (fields may change after it)."""
        from bus.keys import check_vehicle

        if self.algo not in ALGOS:
            raise ConfigError("algo", f"unknown algorithm {self.algo!r}; choose from {ALGOS}")
        if self.reward not in REWARDS:
            raise ConfigError("reward", f"unknown reward {self.reward!r}; choose from "
                                        f"{tuple(REWARDS)}")
        if not self.vehicles:
            raise ConfigError("vehicles", "expected at least one vehicle name or '*'")
        for v in self.vehicles:
            try:
                check_vehicle(v, wildcard=True)
            except ValueError as err:
                raise ConfigError("vehicles", str(err)) from None
        if "*" in self.vehicles and len(self.vehicles) > 1:
            raise ConfigError("vehicles", "'*' (every vehicle) or a list of names, not both")
        check_at_least(self, self.AT_LEAST)
        if self.init_actor not in (None, "scratch"):
            from policy.shipped import policy_path

            try:  # an unknown shipped:NAME, before the bus opens
                policy_path(self.init_actor, flag="--init-actor")
            except ValueError as err:
                raise ConfigError("init_actor", str(err).removeprefix("--init-actor ")) from None
        for name, flag_name in (("updates_per_step", "updates_per_step"), ("grace_s", "grace")):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(flag_name, f"must be a finite number, 0 or more, got {value}")
