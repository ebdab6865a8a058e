"""Training: TD3 or DDPG with a goal-reward variant, in the in-process env (Algorithm 3.1).

``skyloop train --algo td3 --reward abr --scenario valley --episodes 5000 --seed 0 --out DIR``

The task is a skyloop scenario (``policy.training.env.UavNavEnv``) or, with ``env``, any Gymnasium
env id (``policy.training.gym_task.GymTask``: frames stacked the same way, an episodic return of
``goal_return`` or more counts as reaching the goal).

Per env step: act (uniform random for the first ``start_steps``, then the actor plus
Gaussian exploration noise), step the env, store the transition with its *base* reward
(terminal only on collision/goal, never on the 300-step truncation), and, once
``start_steps`` transitions are stored, one agent update. Per episode end: the
goal-reward variant rewrites the episode's rewards in the replay buffer
(TR/NGR/EGR/ABR), a CSV row is written, TensorBoard scalars are logged (below).
``envs`` envs are stepped in turn (``policy.training.collector.Collector``), each its
own stream of episodes in the replay buffer.

TensorBoard, one point per finished episode on two x-axes, each its own run directory so
that a resume purges each at its own step:

- ``OUT/tb``, x = episodes finished: ``episode/return`` (after the goal reward),
  ``episode/steps``, ``episode/success_rate_500``, ``episode/collision_rate_500``,
  ``loss/critic_loss``, ``loss/actor_loss``, ``loss/q1`` (the latest update's; the actor's
  from the latest delayed update), ``time/env_steps_per_s`` (this session's mean) and
  ``time/env_steps``; and the run's hyperparameters (the hparams plugin: the
  ``TrainConfig`` and the agent's config), whose metric is ``episode/success_rate_500``:
  its last value, the run's final success rate.
- ``OUT/tb/env_steps``, x = env steps of all envs together (SB3's ``num_timesteps``): the
  same values under ``env_steps/...`` (``env_steps/return``, ``env_steps/success_rate_500``,
  ``env_steps/actor_loss``, ``env_steps/steps_per_s``, ``env_steps/episodes``, ...).

Two loops over the same bookkeeping:

- ``sync``: the envs and the learner take turns in this process. Reproducible: episode
  ``i`` (the i-th reset) has seed ``seed * 1_000_003 + i``; all other randomness comes
  from generators checkpointed with the networks, optimizers, replay buffer, goal-reward
  state and counters, so the same seed gives the same CSV on the same machine, and with
  one env a resumed run continues exactly as an uninterrupted one.
- parallel (the default): the envs run in a collector process while this process
  updates (``policy.training.collector``); updates per env step stay 1 on average, the collector
  at most ``max_lead`` steps ahead; the learner is one thread (``pipeline`` "off", the
  default), or two with ``pipeline`` "target" (a second thread computes the next TD
  targets, ``policy.algorithms.pipeline``). The same
  episode seeds, network initialisation and random-action phase as ``sync``; *not*
  reproducible: which actor version chose each action after the random phase depends on
  timing, and so does everything after it.

Both run with denormals flushed to zero (``policy.algorithms.td3.flush_denormals``: Adam's moments
of dead units otherwise make every update several times slower) and, with ``precision``
"auto" (the default), in mixed precision (bfloat16 matmuls, ``policy.algorithms.td3``)
where the device multiplies bfloat16 in hardware, else in float32; ``result.json`` and
the agent's checkpointed config say which.

Resumable in both: a checkpoint is written atomically every ``checkpoint_every``
episodes and at the end; ``resume=True`` continues from it, truncating the CSV to the
checkpointed episode count. Episodes in progress at a checkpoint (other envs' streams,
or in the parallel mode the collector's) are cut on resume: their transitions stay in
the buffer with base rewards, and new episodes start with the next seeds.
"""

from __future__ import annotations

import csv
import json
import os
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict
from functools import partial
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from bus.task import TASK, episode_outcome
from perception.observation import ObservationConfig, scaling_fields
from policy.algorithms.agents import make_agent, make_goal_reward
from policy.algorithms.pipeline import TargetPipeline
from policy.algorithms.replay import ReplayBuffer
from policy.algorithms.rewards import RewardConfig
from policy.algorithms.td3 import best_precision, flush_denormals
from policy.training.collector import (
    Collector,
    CollectorSpec,
    SharedActor,
    Transition,
    collector_main,
)
from policy.training.env import EnvConfig, UavNavEnv
from policy.training.plots import CSV_NAME, plot_runs
from policy.training.settings import (  # noqa: F401 - re-exported: the run's config
    Algo,  # lives in the light settings module, so `skyloop train --help` needs no torch
    Precision,
    Reward,
    TrainConfig,
)
from sitl.episode import EpisodeConfig

CHECKPOINT = "checkpoint.pt"
RESULT = "result.json"  # written last: the run is finished
ACTOR = "actor.pt"
#: the state's settings of a checkpoint written before they were options
RESUME_DEFAULTS = {"frames": TASK.frames, "ico_radius": TASK.ico_radius, "encoding": "distance"}
SNAPSHOTS = "snapshots"  # --snapshot-every: actor-ep<N>.pt
REWARD_TERMS = ("progress", "altitude", "heading", "velocity_heading", "collision")
CSV_FIELDS = ["episode", "return", "steps", "outcome", "success_rate_500",
              "collision_rate_500", "total_steps",
              # diagnostics: the base return (before the goal reward; the goal reward's
              # bonus is return - base_return) and its eq. 3.5 terms; ABR's patterns in
              # H, how many of this episode's groups made a new one, and its groups
              "base_return", *(f"r_{k}" for k in REWARD_TERMS),
              "abr_patterns", "abr_new_patterns", "abr_groups",
              "world"]  # the world the episode flew (family:/mix: scenarios draw one)
WINDOW = 500  # success rate over the last 500 episodes (abr-method.md)


def resolve_precision(precision: str, device: str) -> str:
    """``precision`` as the agent takes it: "auto" becomes ``best_precision(device)``."""
    return best_precision(device) if precision == "auto" else precision


def episode_seed(seed: int, episode: int) -> int:
    return seed * 1_000_003 + episode


def make_envs(config: dict, n: int) -> list:
    """``n`` envs of the task (``asdict(TrainConfig)``); picklable for the collector."""
    if config["env"]:
        from policy.training.gym_task import GymTask

        return [GymTask(config["env"], config["goal_return"]) for _ in range(n)]
    env = EnvConfig(frames=config.get("frames", TASK.frames),
                    ico_radius=config.get("ico_radius", TASK.ico_radius),
                    episode=EpisodeConfig(scenario=config["scenario"],
                                          lidar_max_range=config["lidar_max_range"],
                                          world_every=config.get("world_every", 1)))
    observation = ObservationConfig(radius=env.ico_radius,
                                    encoding=config.get("encoding", "distance"))
    return [UavNavEnv(config=env, observation_config=observation) for _ in range(n)]


class Trainer:
    """Owns everything a checkpoint must hold; ``run`` is the loop of Algorithm 3.1."""

    def __init__(self, config: TrainConfig, out: Path) -> None:
        config.validate()
        self.config, self.out = config, Path(out)
        torch.set_num_threads(config.threads)
        torch.manual_seed(config.seed)
        probe = make_envs(asdict(config), 1)[0]  # the sync loop steps it (its env 0)
        if config.env:
            shape, action_dim, self.max_action = probe.state_shape, probe.action_dim, \
                probe.max_action
        else:  # sizes from the env's spaces (the task specification, bus.task)
            shape = probe.observation_space.shape
            action_dim = probe.action_space.shape[0]
            self.max_action = float(probe.action_space.high[0])
        abr = {"p_frames": shape[0], "p_attributes": shape[1]}  # ABR groups p_frames steps
        self._make_agent = partial(make_agent, config.algo, seed=config.seed,
                                   device=config.device, state_dim=int(np.prod(shape)),
                                   action_dim=action_dim, max_action=self.max_action)
        self.agent = self._make_agent(
            precision=resolve_precision(config.precision, config.device))
        self._task = None if config.env else probe.task.to_dict()
        self._observation = None if config.env else scaling_fields(probe.obs_config)
        self.agent.task = self._task  # recorded in the actor files
        self.agent.observation = self._observation
        self._first_env = probe
        self.buffer = ReplayBuffer(config.buffer_size, shape, action_dim, seed=config.seed)
        self.goal_reward = make_goal_reward(config.reward, RewardConfig(), seed=config.seed,
                                            **(abr if config.reward == "abr" else {}))
        self.rng = np.random.default_rng(config.seed)
        self.episode = 0  # episodes finished
        self.started = 0  # episodes begun (their seeds used)
        self.total_steps = 0
        self.wall_s = 0.0  # training wall-clock over all sessions of this run
        self.outcomes: deque[str] = deque(maxlen=WINDOW)
        self.losses: dict[str, float] = {}
        self._open: dict[int, dict] = {}  # stream -> the episode in progress's sums
        # the parallel mode's second learner thread (config.pipeline)
        self._pipeline: TargetPipeline | None = None

    # -- checkpoints ---------------------------------------------------------------

    def state_dict(self) -> dict:
        return {
            "format": "skyloop-train-1",
            "config": asdict(self.config),
            "agent": self.agent.state_dict(),
            "buffer": self.buffer.state_dict(),
            "goal_reward": self.goal_reward.state_dict(),
            "rng": self.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "episode": self.episode,
            "started": self.started,
            "total_steps": self.total_steps,
            "wall_s": self.wall_s,
            "outcomes": list(self.outcomes),
        }

    def save(self) -> None:
        if self._pipeline is not None:
            self._pipeline.settle()  # its worker draws target noise from the agent's state
        tmp = self.out / (CHECKPOINT + ".tmp")
        torch.save(self.state_dict(), tmp)
        os.replace(tmp, self.out / CHECKPOINT)
        self.agent.save_actor(self.out / ACTOR)

    def load(self, path: Path) -> None:
        try:
            state = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as exc:  # torch raises many types for a corrupt file
            raise ValueError(f"{path}: not a readable skyloop checkpoint ({exc})") from exc
        if not isinstance(state, dict) or state.get("format") != "skyloop-train-1":
            raise ValueError(f"{path}: not a skyloop training checkpoint")
        saved = state["config"]
        # what the run learns and the state it reads (a checkpoint from before a field
        # existed: that field's default)
        for key in ("algo", "reward", "scenario", "env", "seed", "frames", "ico_radius",
                    "encoding"):
            had = saved.get(key, RESUME_DEFAULTS.get(key, ""))
            if had != getattr(self.config, key):
                raise ValueError(f"{path}: checkpoint has {key}={had!r} but "
                                 f"this run asks for {getattr(self.config, key)!r}")
        kept = state["agent"]["config"].get("precision", "fp32")
        if kept != self.agent.config.precision:  # a run keeps the arithmetic it began with
            if self.config.precision != "auto":
                raise ValueError(f"{path}: checkpoint was trained with --precision {kept}, "
                                 f"this run asks for {self.config.precision}")
            self.agent = self._make_agent(precision=kept)
            self.agent.task, self.agent.observation = self._task, self._observation
        self.agent.load_state_dict(state["agent"])
        self.buffer.load_state_dict(state["buffer"])
        self.goal_reward.load_state_dict(state["goal_reward"])
        self.rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        self.episode, self.total_steps = state["episode"], state["total_steps"]
        self.started = int(state.get("started", self.episode))
        self.wall_s = float(state.get("wall_s", 0.0))
        self.outcomes = deque(state["outcomes"], maxlen=WINDOW)
        for stream in self.buffer.open_streams():  # cut the episodes in progress
            self.buffer.end_episode(stream=stream)

    # -- bookkeeping shared by both loops --------------------------------------------

    def _act(self, states: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return self.agent.act(states, noise=True, rng=rng)

    def _update(self) -> None:
        # merged: TD3 reports actor_loss only on its delayed steps; keep the latest
        if self._pipeline is not None:
            self.losses.update(self._pipeline.update())
        else:
            batch = self.buffer.sample(self.agent.config.batch_size)
            self.losses.update(self.agent.update(batch))

    def _store(self, tr: Transition) -> None:
        """Add one transition to the replay buffer and to its episode's sums."""
        self.buffer.add(tr.state, tr.action, tr.reward, tr.next_state, tr.terminated,
                        stream=tr.stream)
        self.total_steps += 1
        sums = self._open.get(tr.stream)
        if sums is None:
            self.started += 1
            sums = self._open[tr.stream] = {"steps": 0, "base": 0.0,
                                            "terms": dict.fromkeys(REWARD_TERMS, 0.0)}
        sums["steps"] += 1
        sums["base"] += tr.reward
        for key, value in tr.info.get("reward_components", {}).items():
            sums["terms"][key] += value

    def _end_episode(self, tr: Transition) -> dict:
        """The goal reward rewrites the finished episode of ``tr.stream``; its CSV row."""
        sums = self._open.pop(tr.stream)
        reached = bool(tr.info["goal_reached"])
        outcome = episode_outcome(reached, bool(tr.info["collision"]))
        episode = self.buffer.end_episode(stream=tr.stream)
        rewards = self.goal_reward.on_episode_end(self.buffer, episode, reached)
        groups = getattr(self.goal_reward, "last_groups", []) if reached else []
        self.outcomes.append(outcome)
        self.episode += 1
        return {
            "episode": self.episode, "return": round(float(np.sum(rewards)), 6),
            "steps": sums["steps"], "outcome": outcome,
            "success_rate_500": round(self.outcomes.count("success") / len(self.outcomes), 6),
            "collision_rate_500": round(self.outcomes.count("collision") / len(self.outcomes),
                                        6),
            "total_steps": self.total_steps, "losses": dict(self.losses),
            "base_return": round(sums["base"], 6),
            **{f"r_{k}": round(v, 6) for k, v in sums["terms"].items()},
            "abr_patterns": len(getattr(self.goal_reward, "returns", [])),
            "abr_new_patterns": sum(g.new_pattern for g in groups),
            "abr_groups": len(groups),
            "world": tr.info.get("world", ""),
        }

    def _collector(self, envs: list) -> Collector:
        return Collector(envs, partial(episode_seed, self.config.seed), self.rng,
                         self.max_action, self.agent.config.action_dim,
                         self.config.start_steps, next_episode=self.started,
                         steps=self.total_steps)

    # -- the loops -----------------------------------------------------------------

    def _loop_sync(self, after_episode: Callable[[dict], None]) -> None:
        """Envs and learner in turn (Algorithm 3.1 as written): reproducible."""
        envs = [self._first_env, *make_envs(asdict(self.config), self.config.envs - 1)]
        collector = self._collector(envs)
        while self.episode < self.config.episodes:
            for tr in collector.round(self._act):
                self._store(tr)
                if self.total_steps >= self.config.start_steps:
                    self._update()
                if tr.terminated or tr.truncated:
                    after_episode(self._end_episode(tr))
                    if self.episode >= self.config.episodes:
                        return

    def _loop_parallel(self, after_episode: Callable[[dict], None]) -> None:
        """Envs in a collector process, updates here (see the module docstring)."""
        import torch.multiprocessing as tmp

        c = self.config
        ctx = tmp.get_context("spawn")
        shared = SharedActor(self.agent.actor, ctx)
        shared.publish(self.agent.actor)
        shared.updates.value = self.agent.updates
        a = self.agent.config
        spec = CollectorSpec(
            make_envs=partial(make_envs, asdict(c)), envs=c.envs,
            actor_kwargs={"state_dim": a.state_dim, "action_dim": a.action_dim,
                          "hidden": tuple(a.hidden), "max_action": a.max_action},
            exploration_noise=float(a.exploration_noise), seed=c.seed,
            max_action=self.max_action, action_dim=a.action_dim, start_steps=c.start_steps,
            next_episode=self.started, steps=self.total_steps, max_lead=c.max_lead)
        self._first_env.close()  # the collector makes its own
        recv, send = ctx.Pipe(duplex=False)
        stop = ctx.Event()
        proc = ctx.Process(target=collector_main, daemon=True, name="skyloop-collector",
                           args=(send, spec, shared, stop, partial(episode_seed, c.seed)))
        proc.start()
        send.close()
        delay = a.policy_delay
        sample = partial(self.buffer.sample, a.batch_size)
        if c.pipeline == "target":
            self._pipeline = TargetPipeline(self.agent, sample)
        try:
            while self.episode < c.episodes:
                due = self.total_steps - c.start_steps + 1
                if self.agent.updates < due:
                    self._update()
                    shared.updates.value = self.agent.updates
                    if self.agent.updates % delay == 0:
                        shared.publish(self.agent.actor)
                    if not recv.poll():
                        continue
                elif not recv.poll(1.0):
                    if not proc.is_alive():
                        raise RuntimeError(f"the collector process died (exit code "
                                           f"{proc.exitcode})")
                    continue
                try:
                    batch = recv.recv()
                except EOFError:
                    proc.join(timeout=5)
                    raise RuntimeError(f"the collector process died (exit code "
                                       f"{proc.exitcode})") from None
                for tr in batch:
                    self._store(tr)
                    if tr.terminated or tr.truncated:
                        after_episode(self._end_episode(tr))
                        if self.episode >= c.episodes:
                            break
        finally:
            if self._pipeline is not None:
                self._pipeline.close()
                self._pipeline = None
            stop.set()
            recv.close()
            proc.join(timeout=10)
            if proc.is_alive():
                proc.kill()
                proc.join()
        self._open.clear()

    def run(self, resume: bool = False,
            on_episode: Callable[[dict], None] | None = None) -> dict:
        """Train until ``config.episodes``; ``on_episode(row)`` sees every CSV row.

        Ends by writing ``RESULT`` (the summary), which marks the run finished.
        """
        self.out.mkdir(parents=True, exist_ok=True)
        ckpt = self.out / CHECKPOINT
        csv_path = self.out / CSV_NAME
        if resume:
            if not ckpt.is_file():
                raise FileNotFoundError(f"{ckpt}: nothing to resume")
            self.load(ckpt)
            _truncate_csv(csv_path, self.episode)
        elif ckpt.exists() or csv_path.exists():
            raise FileExistsError(f"{self.out} already holds a run; use --resume or a new --out")
        (self.out / "config.json").write_text(json.dumps(asdict(self.config), indent=2))
        board = Board(self.out / "tb", self.episode, self.total_steps, resume)
        board.start(hparams(self.config, self.agent.config))
        new_file = not csv_path.exists()
        mode = "sync" if self.config.sync else "parallel"
        with csv_path.open("a", newline="") as f, tqdm(
            total=self.config.episodes, initial=self.episode, unit="ep", smoothing=0.05,
            desc=f"{self.config.algo}+{self.config.reward} {self.config.task} "
                 f"({mode}, {self.agent.config.precision})",
            disable=not self.config.progress,
        ) as bar:
            # a resumed run keeps its file's columns (a CSV begun before a column existed)
            rows = csv.DictWriter(f, CSV_FIELDS if new_file else _csv_header(csv_path),
                                  extrasaction="ignore")
            if new_file:
                rows.writeheader()
            t0, steps0, wall0 = time.perf_counter(), self.total_steps, self.wall_s

            def after_episode(row: dict) -> None:
                """Everything after an episode: its CSV row, TensorBoard, the progress
                bar, ``on_episode``, and every ``checkpoint_every`` / ``snapshot_every``
                episodes the checkpoint / an actor snapshot."""
                rows.writerow(row)
                elapsed = time.perf_counter() - t0
                self.wall_s = wall0 + elapsed
                rate = (self.total_steps - steps0) / max(elapsed, 1e-9)
                board.log(row, rate)
                bar.set_postfix(success=f"{row['success_rate_500']:.0%}",
                                steps_s=f"{rate:.0f}", refresh=False)
                bar.update(1)
                if on_episode is not None:
                    on_episode({**row, "env_steps_per_s": rate, "wall_s": self.wall_s})
                if self.episode % self.config.checkpoint_every == 0:
                    f.flush()
                    board.flush()  # what the checkpoint covers is on disk, as the CSV
                    self.save()
                every = self.config.snapshot_every
                if every and self.episode % every == 0:
                    (self.out / SNAPSHOTS).mkdir(exist_ok=True)
                    self.agent.save_actor(self.out / SNAPSHOTS / f"actor-ep{self.episode}.pt")

            try:
                with flush_denormals():  # a large speed-up, see policy.algorithms.td3
                    (self._loop_sync if self.config.sync else self._loop_parallel)(after_episode)
                board.end()  # the hparams session ends as a success
            finally:
                board.close()  # also when a callback or the loop raises
        self.save()
        png = plot_runs([self.out], self.out / "curve.png")
        summary = {"episodes": self.episode, "total_steps": self.total_steps,
                   "success_rate_500": self.outcomes.count("success") / max(len(self.outcomes),
                                                                            1),
                   "wall_s": round(self.wall_s, 1), "mode": mode,
                   "precision": self.agent.config.precision, "curve": str(png),
                   "checkpoint": str(ckpt)}
        (self.out / RESULT).write_text(json.dumps(summary, indent=2))
        return summary


def hparams(config: TrainConfig, agent_config: object) -> dict[str, bool | int | float | str]:
    """The run's hyperparameters for TensorBoard: the ``TrainConfig`` (the task as
    ``task``), then the agent's config fields it does not have; tuples as ``400x300``."""
    skip = {"progress", "extra", "scenario", "env"}
    out: dict[str, bool | int | float | str] = {"task": config.task}
    merged = {**asdict(agent_config), **asdict(config)}  # the run's values win
    for key, value in merged.items():
        if key in skip or value is None:
            continue
        if isinstance(value, (tuple, list)):
            value = "x".join(str(v) for v in value)
        if isinstance(value, (bool, int, float, str)):
            out[key] = value
    return out


class Board:
    """The run's TensorBoard writers: ``dir`` (x = episodes) and ``dir/env_steps``
    (x = env steps); the module docstring lists the tags."""

    METRIC = "episode/success_rate_500"  # the hparams metric: its last value

    def __init__(self, directory: Path, episode: int, env_steps: int, resume: bool) -> None:
        from torch.utils.tensorboard import SummaryWriter

        # A resume drops what was logged after the checkpoint (its episode and env steps
        # are the last ones kept): TensorBoard purges steps >= purge_step on each axis.
        self.episodes = SummaryWriter(str(directory),
                                      purge_step=episode + 1 if resume else None)
        self.env_steps = SummaryWriter(str(directory / "env_steps"),
                                       purge_step=env_steps + 1 if resume else None)

    def start(self, hparam_dict: dict) -> None:
        """The hparams plugin's experiment and session start (the session ends in ``end``)."""
        from torch.utils.tensorboard.summary import hparams as hparams_summaries

        exp, start, self._end = hparams_summaries(hparam_dict, {self.METRIC: 0.0})
        self.episodes.file_writer.add_summary(exp)
        self.episodes.file_writer.add_summary(start)

    def log(self, row: dict, steps_per_s: float) -> None:
        """One finished episode's CSV ``row`` on both axes."""
        ep, n = row["episode"], row["total_steps"]
        values = {key: row[key] for key in ("return", "steps", "success_rate_500",
                                             "collision_rate_500")}
        for key, value in values.items():
            self.episodes.add_scalar(f"episode/{key}", value, ep)
        for key, value in row["losses"].items():
            self.episodes.add_scalar(f"loss/{key}", value, ep)
        self.episodes.add_scalar("time/env_steps_per_s", steps_per_s, ep)
        self.episodes.add_scalar("time/env_steps", n, ep)
        values["episode_steps"] = values.pop("steps")
        for key, value in {**values, **row["losses"], "steps_per_s": steps_per_s,
                           "episodes": ep}.items():
            self.env_steps.add_scalar(f"env_steps/{key}", value, n)

    def end(self) -> None:
        self.episodes.file_writer.add_summary(self._end)

    def flush(self) -> None:
        self.episodes.flush()
        self.env_steps.flush()

    def close(self) -> None:
        self.episodes.close()
        self.env_steps.close()


def finished(out: Path, episodes: int) -> bool:
    """Whether the run in ``out`` has written its result for ``episodes`` episodes."""
    try:
        return json.loads((Path(out) / RESULT).read_text())["episodes"] >= episodes
    except (OSError, ValueError, KeyError, TypeError):
        return False


def _csv_header(path: Path) -> list[str]:
    """The column names of an existing CSV file."""
    with path.open(newline="") as f:
        return next(csv.reader(f), CSV_FIELDS)


def _truncate_csv(path: Path, episodes: int) -> None:
    """Keep the header and the first ``episodes`` rows (those the checkpoint knows)."""
    if not path.exists():
        return
    lines = path.read_bytes().splitlines(keepends=True)  # bytes: keep csv's \r\n
    path.write_bytes(b"".join(lines[: 1 + episodes]))
