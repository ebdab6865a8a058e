"""What the config dataclasses share: an out-of-range setting is a ``ConfigError`` that
names the field and its command-line flag, raised when the dataclass is constructed
(``__post_init__``), so a bad value never gets as far as starting a run. The
``skyloop`` commands whose options are generated from these dataclasses
(``skyloop.cli.dataclass_cli``) print it as argparse's one line:
``skyloop train: error: argument --episodes: must be at least 1, got -1``.

Light on purpose (tyro, no torch, no env): ``TrainConfig`` and ``EvalConfig`` live here so
that ``skyloop train``/``skyloop eval`` answer ``--help`` or a bad command line without
importing torch; ``policy.training.train`` and ``policy.training.evaluate`` re-export them."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, ClassVar, Literal, get_args

import tyro

from bus.task import TASK

__all__ = ["EVAL_SEED", "OFFLINE_UPDATES", "Algo", "ConfigError", "EvalConfig", "Pipeline",
           "Precision",
           "Reward", "TrainConfig", "check_at_least"]

#: the agents (the keys of ``policy.algorithms.agents.ALGOS``) and the goal rewards (of
#: ``policy.algorithms.rewards.GOAL_REWARDS``) a command line may choose (tests check they agree)
Algo = Literal["td3", "ddpg"]
Reward = Literal["tr", "ngr", "egr", "abr"]
#: "auto" and the keys of policy.algorithms.td3.PRECISIONS
Precision = Literal["auto", "fp32", "bf16"]
#: the parallel mode's learner threads (policy.algorithms.pipeline): one; a second for the
#: TD targets (TargetPipeline)
Pipeline = Literal["off", "target"]
#: perception.faces.ENCODINGS
Encoding = Literal["distance", "proximity"]

#: TD3 updates from logs (``skyloop train --from-logs --updates``;
#: ``policy.logs.offline.UPDATES``)
OFFLINE_UPDATES = 10_000
#: the first evaluation seed: above every small-seed run's training episode seeds
#: (``policy.training.evaluate``)
EVAL_SEED = 1_000_000_000


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


@dataclass
class TrainConfig:
    """One training run. Each default here is the only one: ``skyloop train``'s options
    are generated from these fields (``skyloop.cli.train``, with tyro), and grid files
    set them by name (``skyloop.experiment.grid``)."""

    algo: Algo = "td3"
    """the agent"""
    reward: Reward = "abr"
    """the goal reward: TR, NGR, EGR or ABR (abr-method.md)"""
    # sitl/world/families.py; --world-every keeps a drawn world for several episodes
    scenario: str = "valley"
    """a world: valley, forest, city, dynamic, a file, NAME#SEED; or family:NAME, mix:A,B"""
    episodes: int = 5000
    """episodes to train (in total, counting those before a --resume)"""
    seed: int = 0
    """the run's seed (networks, exploration); episode i has seed * 1_000_003 + i"""
    start_steps: int = 10_000
    """initial uniformly random steps (abr-method.md: 10,000)"""
    buffer_size: int = 1_000_000
    """replay buffer capacity in transitions"""
    checkpoint_every: int = 100
    """write a checkpoint every N episodes (and at the end)"""
    snapshot_every: int = 0
    """keep the actor every N episodes as OUT/snapshots/actor-ep<N>.pt, to pick one by
    validation worlds afterwards (0: only the last, OUT/actor.pt)"""
    lidar_max_range: float = 4.5
    """the simulated LiDAR's range, m (the observation needs points within --ico-radius)"""
    # the state's shape (bus.task: recorded in the actor; the stack flies it only with
    # SKY_ICO_RADIUS at the same value and the same number of frames)
    ico_radius: float = TASK.ico_radius
    """p_radius of the observation's truncated icosahedron, m (eq. 3.1; SKY_ICO_RADIUS)"""
    frames: int = TASK.frames
    """p_frames: observations stacked into one state (and ABR's group length)"""
    encoding: Encoding = "distance"
    """the face values: distance from the face centre (eq. 3.2, the paper's) or proximity
    1 - |p| / p_radius (perception/faces.py)"""
    threads: int = 1
    """the learner's torch threads"""
    sync: bool = False
    """envs and learner in turn in one process: reproducible (else a collector process)"""
    envs: int = 1
    """envs stepped in turn by the collector"""
    max_lead: int = 8
    """parallel mode: env steps the collector may run ahead of the updates"""
    pipeline: Pipeline = "off"
    """parallel mode: off, one learner thread (faster in 3 of 4 benchmark runs on two
    machines, benchmarks/RESULTS.md); target: a second thread for the next TD targets
    (policy.algorithms.pipeline)"""
    device: str = "cpu"
    """the learner's device: cpu, cuda, cuda:1, ..."""
    # bf16 = mixed precision: bfloat16 matmuls (AMX/AVX512-BF16 CPUs, GPUs), float32
    # weights and Adam; auto = policy.algorithms.td3.best_precision(device): bf16 where the
    # device multiplies bfloat16 in hardware, else fp32 (the run records which it took)
    precision: Precision = "auto"
    """the update's arithmetic: fp32, bf16 matmuls with float32 weights and Adam, or auto
    (bf16 where the device has bfloat16 matmul units, else fp32)"""
    env: str = ""
    """a Gymnasium env id instead of --scenario, e.g. BipedalWalkerHardcore-v3"""
    world_every: int = 1
    """family:/mix: scenarios: a new world every N episodes"""
    goal_return: float = 0.0
    """with --env: the episodic return that counts as reaching the goal"""
    # not flags: the tqdm bar (off under Ray Tune, which reports for itself), and
    # free-form entries recorded in the run's config.json
    progress: tyro.conf.Suppress[bool] = True
    extra: tyro.conf.Suppress[dict] = field(default_factory=dict)

    # the least value of each count; a smaller one is refused on construction
    AT_LEAST: ClassVar[dict[str, int]] = {
        "episodes": 1, "start_steps": 0, "buffer_size": 1, "checkpoint_every": 1,
        "threads": 1, "envs": 1, "max_lead": 1, "world_every": 1,
        "snapshot_every": 0, "frames": 2}  # frames: ABR's feature CNN convolves 2

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> None:
        """The cheap checks: counts in range, choices among the known ones. Raises
        ``ConfigError`` naming the flag; runs on construction, so a bad value never
        gets as far as starting a run."""
        check_at_least(self, self.AT_LEAST)
        # the Literals' choices (tests check they are ALGOS, GOAL_REWARDS, PRECISIONS)
        if self.algo not in get_args(Algo):
            raise ConfigError("algo", f"unknown algorithm {self.algo!r}; choose from "
                                      f"{sorted(get_args(Algo))}")
        if self.reward not in get_args(Reward):
            raise ConfigError("reward", f"unknown reward {self.reward!r}; choose from "
                                        f"{sorted(get_args(Reward))}")
        if self.pipeline not in get_args(Pipeline):
            raise ConfigError("pipeline", f"must be one of {sorted(get_args(Pipeline))}, "
                                          f"got {self.pipeline!r}")
        if self.encoding not in get_args(Encoding):
            raise ConfigError("encoding", f"must be one of {sorted(get_args(Encoding))}, "
                                          f"got {self.encoding!r}")
        if self.precision not in get_args(Precision):
            raise ConfigError("precision", f"must be one of {sorted(get_args(Precision))}, "
                                           f"got {self.precision!r}")
        if not 0.5 <= self.ico_radius <= 50.0:  # SKY_ICO_RADIUS's range (bus.params)
            raise ConfigError("ico_radius", f"must be in [0.5, 50] m, got {self.ico_radius}")
        if self.env and self.frames != TASK.frames:
            raise ConfigError("frames", f"is for the skyloop task; a Gymnasium env's state "
                                        f"stacks {TASK.frames} (policy.training.gym_task)")
        if self.ico_radius > self.lidar_max_range and not self.env:
            raise ConfigError("ico_radius", f"{self.ico_radius} m is beyond the LiDAR's range "
                                            f"(--lidar-max-range {self.lidar_max_range}): the "
                                            f"faces would never see that far")

    def validate(self) -> None:
        """``check``, then what costs more: the device, the scenario or env id."""
        import torch

        from sitl.world.families import check_scenario  # ScenarioError naming the scenario

        self.check()  # the fields may have been changed since construction
        try:
            torch.empty(0, device=self.device)
        except (RuntimeError, AssertionError) as exc:
            raise ValueError(f"--device {self.device!r} is not usable here ({exc})") from exc
        if self.env:
            from policy.training.gym_task import check_env_id

            check_env_id(self.env)
        else:
            check_scenario(self.scenario)

    @property
    def task(self) -> str:
        """What the run learns: the Gymnasium env id or the scenario name."""
        return self.env or self.scenario


@dataclass
class EvalConfig:
    """One evaluation (``policy.training.evaluate.evaluate``'s arguments). ``skyloop eval``'s
    options are generated from these fields (``skyloop.cli.dataclass_cli``, with tyro): each
    default lives here."""

    policy: Annotated[str | None, tyro.conf.arg(
        metavar="ACTOR|RUN_DIR|scripted|shipped[:NAME]")] = None
    """actor file or run directory (its actor.pt), scripted, or an actor skyloop ships
    (shipped:NAME, policy/shipped/__init__.py); None: the default shipped policy"""
    scenario: str = "valley"
    """a world, or family:NAME with --worlds"""
    # world seeds never drawn in training (sitl/world/families.py)
    worlds: Annotated[int | None, tyro.conf.arg(metavar="N")] = None
    """with --scenario family:NAME: fly N held-out worlds of the family, episodes spread"""
    validation: bool = False
    """with --worlds: the validation worlds instead (to choose among trained policies)"""
    episodes: int = 500
    """episodes to fly"""
    seed: int = EVAL_SEED
    """episode i's seed is SEED + i (the default: seeds no training run draws)"""
    json_path: Annotated[Path | None, tyro.conf.arg(name="json", metavar="PATH")] = None
    """write the summary as JSON here"""

    AT_LEAST: ClassVar[dict[str, int]] = {"episodes": 1, "worlds": 1}

    def __post_init__(self) -> None:
        check_at_least(self, self.AT_LEAST)
