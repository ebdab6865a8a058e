"""What the config dataclasses share: an out-of-range setting is a ``ConfigError`` that
names the field and its command-line flag, raised when the dataclass is constructed
(``__post_init__``), so a bad value never gets as far as starting a run. The
``skyloop`` commands whose options are generated from these dataclasses
(``skyloop.dataclass_cli``) print it as argparse's one line:
``skyloop train: error: argument --episodes: must be at least 1, got -1``."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Literal

__all__ = ["Algo", "ConfigError", "Reward", "check_at_least"]

#: the agents (the keys of ``policy.algorithms.agents.ALGOS``) and the goal rewards (of
#: ``policy.algorithms.rewards.GOAL_REWARDS``) a command line may choose (tests check they agree)
Algo = Literal["td3", "ddpg"]
Reward = Literal["tr", "ngr", "egr", "abr"]


class ConfigError(ValueError):
    """A setting out of range or not among its choices. Names the field (``name``) and
    its flag (``flag``); ``str()`` is ``"--flag: problem"``."""

    def __init__(self, name: str, problem: str) -> None:
        self.name = name
        self.flag = "--" + name.replace("_", "-")
        self.problem = problem
        super().__init__(f"{self.flag}: {problem}")


def check_at_least(config: object, least: Mapping[str, int]) -> None:
    """Each named integer field of ``config`` is at least its least value (a field that
    is None, an optional count left out, passes)."""
    for name, bound in least.items():
        value = getattr(config, name)
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(name, f"must be an integer, got {value!r}")
        if value < bound:
            word = "0 or more" if bound == 0 else f"at least {bound}"
            raise ConfigError(name, f"must be {word}, got {value}")
