"""The learning algorithms by name, for the trainer and the command line."""

from __future__ import annotations

from policy.ddpg import DDPG, DDPGConfig
from policy.td3 import TD3, TD3Config

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
