"""Evaluation: a deterministic actor (no exploration noise) over seeded episodes.

``skyloop eval [--policy CKPT|scripted] --scenario NAME --episodes N --seed S [--json PATH]``

Episode ``i`` is reset with seed ``S + i``. Training episodes use seeds
``train_seed * 1_000_003 + i`` (``policy.training.train``), so the default evaluation seed
``EVAL_SEED`` = 1,000,000,000 gives episodes no small-seed training run has seen.
Rates carry 95% Wilson intervals (``policy.training.rollout``).
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from bus.task import TASK, TaskSpec
from perception.observation import ObservationConfig, config_from_scaling
from policy.algorithms.scripted import StraightLineController
from policy.algorithms.td3 import load_actor
from policy.shipped import (  # noqa: F401 - SHIPPED_POLICY re-exported
    SHIPPED,
    SHIPPED_POLICY,
    policy_path,
    shipped_actor,
)
from policy.training.env import EnvConfig, UavNavEnv
from policy.training.rollout import run_episode, summarize
from policy.training.settings import (  # noqa: F401 - re-exported: EvalConfig lives in the
    EVAL_SEED,  # light settings module, so `skyloop eval --help` needs no torch
    EvalConfig,
)
from sitl.episode import LIDAR_MARGIN, EpisodeConfig


def _torch_error(path: Path, exc: Exception) -> str:
    """A short reason from what ``torch.load`` raised (its advice about ``weights_only``
    misleads for a file that is not a torch file at all)."""
    if not zipfile.is_zipfile(path):
        return "not a torch file"
    text = str(exc).strip()
    if "weights_only" in text:
        return "a torch file, but not an actor (a training checkpoint? use its run's actor.pt)"
    return text.splitlines()[0][:200] if text else type(exc).__name__


class ActorController:
    """The deterministic actor mu(s) of a trained agent as a controller."""

    def __init__(self, path: str | Path, task: TaskSpec | None = TASK) -> None:
        """``path``: what :func:`policy_path` takes; ``task``: the skyloop task it must fly
        (None: any, e.g. a Gymnasium env's)."""
        path = policy_path(path)
        if path.is_dir():  # a training run's directory: its actor
            if not (path / "actor.pt").is_file():
                raise FileNotFoundError(f"{path}: a directory without an actor.pt")
            path = path / "actor.pt"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such policy file or directory")
        try:
            self.actor = load_actor(path, task=task)
        except ValueError:
            raise
        except Exception as exc:  # torch raises many types for a corrupt file
            raise ValueError(f"{path}: not a readable skyloop actor "
                             f"({_torch_error(path, exc)})") from exc
        #: the task it was trained under (files that do not say: the default task's)
        self.trained_task: TaskSpec = self.actor.trained_task or TASK
        #: how the observations it was trained on were made (files that do not say:
        #: the default configuration at the task's radius)
        recorded = self.actor.trained_observation
        try:
            self.trained_observation = (config_from_scaling(recorded) if recorded else
                                        ObservationConfig(radius=self.trained_task.ico_radius))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: its recorded observation {recorded!r} is not one "
                             f"({exc})") from None
        shipped = [n for n in SHIPPED if path.resolve() == shipped_actor(n)]
        self.name = (f"shipped TD3+ABR policy {shipped[0]!r} ({path})" if shipped
                     else f"actor {path}")
        self.inputs = inputs = self.actor.net[0].in_features
        self.outputs = outputs = self.actor.net[-2].out_features
        self.records_task = self.actor.trained_task is not None
        if task is not None and (inputs, outputs) != (task.state_dim, task.action_dim):
            raise ValueError(f"{path}: an actor for {inputs} inputs and {outputs} actions; "
                             f"this task has {task.state_dim} and {task.action_dim}")
        probe = self(np.zeros(inputs, np.float32))  # the all-zero first state
        if not np.all(np.isfinite(probe)):
            raise ValueError(f"{path}: the actor outputs {probe.tolist()} for the "
                             f"all-zero state; its weights are broken (NaN or inf)")

    @torch.no_grad()
    def __call__(self, state: np.ndarray) -> np.ndarray:
        x = torch.as_tensor(np.asarray(state, np.float32).reshape(1, -1))
        return self.actor(x)[0].numpy()


def make_controller(policy: str | None, task: TaskSpec | None = TASK):
    """``"scripted"`` -> the straight-line baseline; otherwise the actor
    :func:`policy_path` names (``None``: the default shipped policy). ``task``: the task
    the actor must fly (None: the one it was trained for)."""
    if policy == "scripted":
        return StraightLineController()
    return ActorController(policy_path(policy), task=task)


def stack_controller(policy: str | None):
    """What the stack's policy node flies (``skyloop policy``): ``make_controller``'s
    controller for the skyloop task at the frames the actor was trained with (the node
    stacks that many; the state's other fields, faces and actions, must be the task's)."""
    controller = make_controller(policy, task=None)
    trained = getattr(controller, "trained_task", None)
    if trained is None or trained.frames == TASK.frames:
        return make_controller(policy)  # checked against the task itself
    return make_controller(policy, task=replace(TASK, frames=trained.frames))


def env_for(controller, scenario: str) -> UavNavEnv:
    """The in-process env in the state ``controller`` was trained to read: its recorded
    frames, icosahedron radius (LiDAR range radius + ``LIDAR_MARGIN``) and observation
    (the scripted controller and actors that record none: the default task's). An actor
    whose input or output size does not fit that state is a ``ValueError``."""
    trained = getattr(controller, "trained_task", None) or TASK
    inputs, outputs = getattr(controller, "inputs", None), getattr(controller, "outputs", None)
    if inputs is not None and (inputs, outputs) != (trained.state_dim, trained.action_dim):
        what = ("it records a task of" if getattr(controller, "records_task", False)
                else "it records no task; the default task has")
        raise ValueError(f"{controller.name}: an actor for {inputs} inputs and {outputs} "
                         f"actions; {what} {trained.state_dim} and {trained.action_dim}")
    return UavNavEnv(config=EnvConfig(
        frames=trained.frames, ico_radius=trained.ico_radius,
        episode=EpisodeConfig(scenario=scenario,
                              lidar_max_range=trained.ico_radius + LIDAR_MARGIN)),
        observation_config=getattr(controller, "trained_observation", None))


def evaluate(policy: str | None, scenario: str, episodes: int, seed: int = EVAL_SEED,
             json_path: Path | None = None, progress: bool = True, *,
             worlds: int | None = None, validation: bool = False) -> dict:
    """Fly ``episodes`` deterministic episodes (seeds ``seed, seed + 1, ...``). With
    ``scenario="family:NAME"`` and ``worlds=N``: episode ``i`` flies held-out world
    ``i % N`` of the family (``sitl.world.families.eval_worlds``; ``validation``: the
    validation worlds), never one drawn in training."""
    from sitl.world.families import WorldSource, eval_worlds

    source = WorldSource.parse(scenario)
    if worlds is not None and not scenario.startswith("family:"):  # one family, parsed
        raise ValueError(f"--worlds needs --scenario family:NAME, got {scenario!r}")
    if worlds is not None and worlds < 1:
        raise ValueError(f"--worlds: expected a positive integer, got {worlds}")
    if worlds is None and not source.fixed:
        raise ValueError(f"--scenario {scenario}: evaluation flies held-out worlds: give "
                         f"--worlds N")
    names = ([] if worlds is None
             else eval_worlds(source.families[0], worlds, validation=validation))
    torch.set_num_threads(1)
    controller = make_controller(policy, task=None)
    env = env_for(controller, names[0] if names else scenario)
    trained = env.task
    results = []
    for i in tqdm(range(episodes), total=episodes, unit="ep", disable=not progress,
                  desc=f"eval {scenario}"):
        if names:
            env.sim.use_world(names[i % len(names)])
        results.append(run_episode(env, controller, seed + i))
    env.close()
    summary = summarize(results)
    summary.update(policy=controller.name, scenario=scenario, seed=seed,
                   task={"frames": trained.frames, "ico_radius": trained.ico_radius,
                         "encoding": env.obs_config.encoding})
    if names:
        summary.update(worlds=len(names), world_seeds=[int(n.rpartition("#")[2])
                                                       for n in (names[0], names[-1])],
                       world_set="validation" if validation else "held-out")
    if json_path:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(summary, indent=2))
    return summary


def format_summary(s: dict) -> str:
    lo, hi = s["success_ci95"]
    where = (f" ({s['worlds']} {s['world_set']} worlds, seeds {s['world_seeds'][0]}-"
             f"{s['world_seeds'][1]})" if "worlds" in s else "")
    task = s.get("task", {})
    default = (TASK.frames, TASK.ico_radius, ObservationConfig.encoding)
    if task and (task["frames"], task["ico_radius"], task.get("encoding")) != default:
        where += (f" (its state: {task['frames']} frames, icosahedron radius "
                  f"{task['ico_radius']:g} m, {task.get('encoding')} encoding)")
    return (f"{s['policy']} on {s['scenario']}{where}: {s['episodes']} episodes from seed "
            f"{s['seed']}: "
            f"success {s['success_rate']:.1%} (95% CI {lo:.1%}-{hi:.1%}), "
            f"collision {s['collision_rate']:.1%}, timeout {s['timeout_rate']:.1%}, "
            f"mean steps {s['mean_steps']:.1f}, mean path {s['mean_path_length']:.1f} m")
