"""The learning algorithms and the goal rewards by name, for the trainers and the
command line."""

from __future__ import annotations

from typing import Any

from policy.algorithms.abr import ABRConfig, AugmentativeBackwardReward
from policy.algorithms.ddpg import DDPG, DDPGConfig
from policy.algorithms.rewards import (
    GOAL_REWARDS,
    EqualGoalReward,
    GoalReward,
    NoGoalReward,
    RewardConfig,
    TraditionalReward,
)
from policy.algorithms.td3 import TD3, TD3Config

ALGOS: dict[str, tuple[type[TD3], type[TD3Config]]] = {
    "td3": (TD3, TD3Config),
    "ddpg": (DDPG, DDPGConfig),
}


def make_agent(name: str, seed: int = 0, device: str = "cpu", **overrides) -> TD3:
    """A fresh agent with the paper's hyperparameters (abr-method.md) and ``seed``, its
    networks on ``device`` ("cpu", "cuda", "cuda:1", ...)."""
    if name not in ALGOS:
        raise ValueError(f"unknown algorithm {name!r}; choose from {sorted(ALGOS)}")
    cls, config_cls = ALGOS[name]
    return cls(config_cls(seed=seed, **overrides), device=device)


def make_goal_reward(
    name: str, config: RewardConfig | None = None, **abr_kwargs: Any
) -> GoalReward:
    """Build a goal-reward variant by name: ``tr``, ``ngr``, ``egr`` or ``abr``
    (``abr_kwargs`` go to :class:`policy.algorithms.abr.ABRConfig`)."""
    key = name.lower()
    if key == "tr":
        return TraditionalReward(config)
    if key == "ngr":
        return NoGoalReward(config)
    if key == "egr":
        return EqualGoalReward(config)
    if key == "abr":
        return AugmentativeBackwardReward(ABRConfig(**abr_kwargs))
    raise ValueError(f"unknown goal reward {name!r}; expected one of {GOAL_REWARDS}")
