"""Run a controller for whole episodes in the in-process env and summarise the outcomes.

Used by ``skyloop demo`` and evaluation. Outcome per episode: ``success`` (goal
reached), ``collision`` or ``timeout`` (the 300-step truncation). Rates carry 95%
Wilson score intervals (Wilson 1927), which behave at 0% and 100% where the normal
approximation does not.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from bus.task import episode_outcome

Controller = Callable[[np.ndarray], np.ndarray]


@dataclass
class EpisodeResult:
    seed: int
    outcome: str  # "success" | "collision" | "timeout"
    steps: int
    episode_return: float
    path_length: float
    path: np.ndarray = field(repr=False)
    start: np.ndarray = field(repr=False)
    goal: np.ndarray = field(repr=False)


def run_episode(env, controller: Controller, seed: int) -> EpisodeResult:
    """One episode with ``env.reset(seed=seed)``; the controller sees the stacked state."""
    state, info = env.reset(seed=seed)
    total = 0.0
    while True:
        state, reward, terminated, truncated, info = env.step(controller(state))
        total += reward
        if terminated or truncated:
            break
    outcome = episode_outcome(info["goal_reached"], info["collision"])
    base = env.unwrapped
    path = np.array(base.path)
    length = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
    return EpisodeResult(seed, outcome, info["steps"], total, length, path, base.start, base.goal)


def run_episodes(
    env, controller: Controller, episodes: int, seed: int
) -> Iterator[EpisodeResult]:
    """Episodes with seeds ``seed, seed + 1, ...`` (each reproducible on its own)."""
    for i in range(episodes):
        yield run_episode(env, controller, seed + i)


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """95% Wilson score interval for a binomial proportion."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def summarize(results: list[EpisodeResult]) -> dict:
    """Rates with Wilson intervals, mean steps and mean path length."""
    n = len(results)
    out: dict = {"episodes": n}
    for outcome in ("success", "collision", "timeout"):
        k = sum(r.outcome == outcome for r in results)
        out[f"{outcome}_rate"] = k / n if n else 0.0
        out[f"{outcome}_ci95"] = list(wilson_interval(k, n))
    out["mean_steps"] = float(np.mean([r.steps for r in results])) if n else 0.0
    out["mean_path_length"] = float(np.mean([r.path_length for r in results])) if n else 0.0
    out["mean_return"] = float(np.mean([r.episode_return for r in results])) if n else 0.0
    return out
