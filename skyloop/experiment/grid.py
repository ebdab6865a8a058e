"""Grid files: which ``skyloop train`` runs an experiment is made of (pure, no Ray).

A grid file is TOML; every trial is one ``skyloop train`` run
(``policy.training.settings.TrainConfig``) and the grid is the product of its tasks, methods
and seeds::

    name = "paper_static"
    scenarios = ["valley"]            # skyloop scenarios, and/or
    envs = ["BipedalWalkerHardcore-v3"]   # Gymnasium env ids
    methods = ["ddpg+tr", "td3+tr", "td3+abr"]   # algo+reward; or algos = [...] x rewards = [...]
    seeds = [0, 1, 2]
    episodes = 3000

    [train]                           # any other TrainConfig option, for every trial
    checkpoint_every = 100
    goal_return = 0.0                 # with envs: the return that counts as the goal

``scenario`` / ``env`` (one string) may stand for the lists. Every mistake is a
``GridError`` naming the file and the field, raised before anything runs.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from policy.training.settings import ConfigError, TrainConfig

__all__ = ["Grid", "GridError", "Trial", "load_grid"]

TOP_LEVEL = {"name", "scenario", "scenarios", "env", "envs", "methods", "algos", "rewards",
             "seeds", "episodes", "train"}
# TrainConfig fields a grid sets at the top level or per trial, never in [train]
PER_TRIAL = {"algo", "reward", "scenario", "env", "seed", "episodes"}
NOT_IN_GRID = {"extra", "progress"}


class GridError(ValueError):
    """A grid file that cannot run; the message names the file and the field."""


@dataclass(frozen=True)
class Trial:
    """One run of the grid: its name (its directory under the output) and its config."""

    name: str
    config: TrainConfig

    @property
    def method(self) -> str:
        return f"{self.config.algo}+{self.config.reward}"


@dataclass(frozen=True)
class Grid:
    name: str
    path: Path
    trials: tuple[Trial, ...]

    @property
    def episodes(self) -> int:
        return sum(t.config.episodes for t in self.trials)


def _strings(path: Path, data: dict, key: str) -> list[str]:
    value = data[key]
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not value or not all(isinstance(v, str) and v
                                                           for v in value):
        raise GridError(f"{path}: {key}: expected a non-empty list of strings, got {value!r}")
    return value


def _methods(path: Path, data: dict) -> list[tuple[str, str]]:
    from policy.algorithms.agents import ALGOS
    from policy.algorithms.rewards import GOAL_REWARDS

    if "methods" in data:
        if "algos" in data or "rewards" in data:
            raise GridError(f"{path}: methods: give either methods or algos x rewards, not both")
        pairs = []
        for m in _strings(path, data, "methods"):
            algo, sep, reward = m.partition("+")
            if not sep:
                raise GridError(f"{path}: methods: {m!r} is not 'algo+reward' (e.g. 'td3+abr')")
            pairs.append((algo, reward))
    elif "algos" in data and "rewards" in data:
        pairs = [(a, r) for a in _strings(path, data, "algos")
                 for r in _strings(path, data, "rewards")]
    else:
        raise GridError(f"{path}: methods: missing (give methods, or algos and rewards)")
    for algo, reward in pairs:
        if algo not in ALGOS:
            raise GridError(f"{path}: methods: unknown algorithm {algo!r}; "
                            f"choose from {sorted(ALGOS)}")
        if reward not in GOAL_REWARDS:
            raise GridError(f"{path}: methods: unknown reward {reward!r}; "
                            f"choose from {sorted(GOAL_REWARDS)}")
    return pairs


def _tasks(path: Path, data: dict) -> list[tuple[str, str]]:
    """(kind, name) pairs: ("scenario", "valley") or ("env", "BipedalWalkerHardcore-v3")."""
    from policy.training.gym_task import check_env_id
    from sitl.world.families import check_scenario

    tasks: list[tuple[str, str]] = []
    for kind in ("scenario", "env"):
        for key in (kind, kind + "s"):
            if key not in data:
                continue
            for name in _strings(path, data, key):
                try:
                    check_scenario(name) if kind == "scenario" else check_env_id(name)
                except Exception as exc:  # ScenarioError, ValueError: name the field
                    raise GridError(f"{path}: {key}: {exc}") from exc
                tasks.append((kind, name))
    if not tasks:
        raise GridError(f"{path}: scenarios: missing (give scenarios and/or envs)")
    return tasks


def _seeds(path: Path, data: dict) -> list[int]:
    seeds = data.get("seeds")
    if not isinstance(seeds, list) or not seeds:
        raise GridError(f"{path}: seeds: expected a non-empty list of integers, got {seeds!r}")
    for s in seeds:
        if isinstance(s, bool) or not isinstance(s, int) or s < 0:
            raise GridError(f"{path}: seeds: {s!r} is not a non-negative integer")
    if len(set(seeds)) != len(seeds):
        raise GridError(f"{path}: seeds: repeated seed in {seeds}")
    return seeds


def _train_options(path: Path, data: dict) -> dict[str, Any]:
    options = data.get("train", {})
    if not isinstance(options, dict):
        raise GridError(f"{path}: train: expected a table of skyloop train options")
    known = {f.name: f for f in fields(TrainConfig)}
    defaults = asdict(TrainConfig())
    for key, value in options.items():
        if key in PER_TRIAL:
            raise GridError(f"{path}: train.{key}: set it at the top level of the grid")
        if key not in known or key in NOT_IN_GRID:
            allowed = sorted(set(known) - PER_TRIAL - NOT_IN_GRID)
            raise GridError(f"{path}: train.{key}: unknown option; choose from {allowed}")
        want = type(defaults[key])
        ok = isinstance(value, want) or (want is float and isinstance(value, int))
        if not ok or isinstance(value, bool) != (want is bool):
            raise GridError(f"{path}: train.{key}: expected {want.__name__}, got {value!r}")
    return options


def load_grid(path: str | Path) -> Grid:
    """Read and check a grid file; every trial's config is validated before returning."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise GridError(f"{path}: cannot read the grid file ({exc.strerror})") from exc
    except tomllib.TOMLDecodeError as exc:
        raise GridError(f"{path}: not valid TOML ({exc})") from exc
    for key in data:
        if key not in TOP_LEVEL:
            raise GridError(f"{path}: {key}: unknown field; choose from {sorted(TOP_LEVEL)}")
    episodes = data.get("episodes")
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise GridError(f"{path}: episodes: expected a positive integer, got {episodes!r}")
    name = data.get("name", path.stem)
    if not isinstance(name, str) or not name:
        raise GridError(f"{path}: name: expected a non-empty string, got {name!r}")
    tasks, methods, seeds = _tasks(path, data), _methods(path, data), _seeds(path, data)
    options = _train_options(path, data)
    trials = []
    for seed in seeds:  # seed-major: every method's first seed runs first
        for kind, task in tasks:
            for algo, reward in methods:
                try:
                    config = TrainConfig(algo=algo, reward=reward, seed=seed,
                                         episodes=episodes, progress=False, **{kind: task},
                                         **options)
                except ConfigError as exc:  # a value out of range, e.g. checkpoint_every = 0
                    key = f"train.{exc.name}" if exc.name in options else exc.name
                    raise GridError(f"{path}: {key}: {exc.problem}") from exc
                slug = re.sub(r"[^A-Za-z0-9_.+#=-]", "_", task)  # mix:a,b -> mix_a_b
                trials.append(Trial(f"{slug}-{algo}+{reward}-s{seed}", config))
    if len({t.name for t in trials}) != len(trials):
        raise GridError(f"{path}: methods: the grid names the same trial twice")
    return Grid(name, path, tuple(trials))
