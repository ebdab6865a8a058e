"""Training: TD3 or DDPG with a goal-reward variant, in the in-process env (Algorithm 3.1).

``skyloop train --algo td3 --reward abr --scenario valley --episodes 5000 --seed 0 --out DIR``

The task is a skyloop scenario (``policy.env.UavNavEnv``) or, with ``env``, any Gymnasium
env id (``policy.gym_task.GymTask``: frames stacked the same way, an episodic return of
``goal_return`` or more counts as reaching the goal).

Per step: act (uniform random for the first ``start_steps``, then the actor plus
Gaussian exploration noise), step the env, store the transition with its *base* reward
(terminal only on collision/goal, never on the 300-step truncation), update the agent
once. Per episode end: the goal-reward variant rewrites the episode's rewards in the
replay buffer (TR/NGR/EGR/ABR), a CSV row is written, TensorBoard scalars are logged.

Reproducible and resumable: episode ``i`` is reset with seed ``seed * 1_000_003 + i``;
all other randomness comes from generators whose states are checkpointed together with
the networks, optimizers, replay buffer, goal-reward state and counters. A checkpoint is
written atomically every ``checkpoint_every`` episodes and at the end; ``resume=True``
continues from it, truncating the CSV to the checkpointed episode count. The CSV holds
no wall-clock columns, so the same seed gives the same CSV on the same machine.
"""

from __future__ import annotations

import csv
import json
import os
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from policy.agents import ALGOS, make_agent
from policy.env import UavNavEnv
from policy.plots import CSV_NAME, plot_runs
from policy.replay import ReplayBuffer
from policy.rewards import GOAL_REWARDS, RewardConfig, make_goal_reward

CHECKPOINT = "checkpoint.pt"
RESULT = "result.json"  # written last: the run is finished
ACTOR = "actor.pt"
REWARD_TERMS = ("progress", "altitude", "heading", "velocity_heading", "collision")
CSV_FIELDS = ["episode", "return", "steps", "outcome", "success_rate_500",
              "collision_rate_500", "total_steps",
              # diagnostics: the base return (before the goal reward; the goal reward's
              # bonus is return - base_return) and its eq. 3.5 terms; ABR's patterns in
              # H, how many of this episode's groups made a new one, and its groups
              "base_return", *(f"r_{k}" for k in REWARD_TERMS),
              "abr_patterns", "abr_new_patterns", "abr_groups"]
WINDOW = 500  # success rate over the last 500 episodes (abr-method.md)


@dataclass
class TrainConfig:
    algo: str = "td3"
    reward: str = "abr"
    scenario: str = "valley"
    episodes: int = 5000
    seed: int = 0
    start_steps: int = 10_000  # initial uniform-random steps [choice, abr-method.md]
    buffer_size: int = 1_000_000
    checkpoint_every: int = 100
    lidar_max_range: float = 4.5
    threads: int = 1
    env: str = ""  # a Gymnasium env id instead of a scenario (the paper's BipedalWalker)
    goal_return: float = 0.0  # with env: the episodic return that counts as the goal
    progress: bool = True  # the tqdm bar (off under Ray Tune, which reports for itself)
    extra: dict = field(default_factory=dict)

    def validate(self) -> None:
        from sitl.world import load_scenario  # raises ScenarioError naming the scenario

        if self.algo not in ALGOS:
            raise ValueError(f"unknown algorithm {self.algo!r}; choose from {sorted(ALGOS)}")
        if self.reward not in GOAL_REWARDS:
            raise ValueError(f"unknown reward {self.reward!r}; choose from {sorted(GOAL_REWARDS)}")
        if self.episodes < 1:
            raise ValueError(f"--episodes must be >= 1, got {self.episodes}")
        if self.env:
            from policy.gym_task import check_env_id

            check_env_id(self.env)
        else:
            load_scenario(self.scenario)

    @property
    def task(self) -> str:
        """What the run learns: the Gymnasium env id or the scenario name."""
        return self.env or self.scenario


def episode_seed(seed: int, episode: int) -> int:
    return seed * 1_000_003 + episode


class Trainer:
    """Owns everything a checkpoint must hold; ``run`` is the loop of Algorithm 3.1."""

    def __init__(self, config: TrainConfig, out: Path) -> None:
        config.validate()
        self.config, self.out = config, Path(out)
        torch.set_num_threads(config.threads)
        torch.manual_seed(config.seed)
        if config.env:
            from policy.gym_task import GymTask

            self.env = GymTask(config.env, config.goal_return)
            shape, action_dim = self.env.state_shape, self.env.action_dim
            self.max_action = self.env.max_action
            self.agent = make_agent(config.algo, seed=config.seed, state_dim=int(np.prod(shape)),
                                    action_dim=action_dim, max_action=self.max_action)
            abr = {"p_frames": shape[0], "p_attributes": shape[1]}
        else:
            self.env = UavNavEnv(scenario=config.scenario,
                                 lidar_max_range=config.lidar_max_range)
            shape, action_dim, self.max_action = (3, 35), 4, 2.0
            self.agent = make_agent(config.algo, seed=config.seed)
            abr = {}
        self.buffer = ReplayBuffer(config.buffer_size, shape, action_dim, seed=config.seed)
        self.goal_reward = make_goal_reward(config.reward, RewardConfig(), seed=config.seed,
                                            **(abr if config.reward == "abr" else {}))
        self.rng = np.random.default_rng(config.seed)
        self.episode = 0
        self.total_steps = 0
        self.wall_s = 0.0  # training wall-clock over all sessions of this run
        self.outcomes: deque[str] = deque(maxlen=WINDOW)

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
            "total_steps": self.total_steps,
            "wall_s": self.wall_s,
            "outcomes": list(self.outcomes),
        }

    def save(self) -> None:
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
        for key in ("algo", "reward", "scenario", "env", "seed"):
            if saved.get(key, "") != getattr(self.config, key):
                raise ValueError(f"{path}: checkpoint has {key}={saved[key]!r} but this run "
                                 f"asks for {getattr(self.config, key)!r}")
        self.agent.load_state_dict(state["agent"])
        self.buffer.load_state_dict(state["buffer"])
        self.goal_reward.load_state_dict(state["goal_reward"])
        self.rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        self.episode, self.total_steps = state["episode"], state["total_steps"]
        self.wall_s = float(state.get("wall_s", 0.0))
        self.outcomes = deque(state["outcomes"], maxlen=WINDOW)

    # -- the loop ------------------------------------------------------------------

    def act(self, state: np.ndarray) -> np.ndarray:
        if self.total_steps < self.config.start_steps:
            return self.rng.uniform(-self.max_action, self.max_action,
                                    self.agent.config.action_dim).astype(np.float32)
        return self.agent.act(state, noise=True, rng=self.rng)

    def run_episode(self) -> dict:
        state, _ = self.env.reset(seed=episode_seed(self.config.seed, self.episode))
        total, steps, losses = 0.0, 0, {}
        terms = dict.fromkeys(REWARD_TERMS, 0.0)
        while True:
            action = self.act(state)
            next_state, reward, terminated, truncated, info = self.env.step(action)
            self.buffer.add(state, action, reward, next_state, terminated)
            self.total_steps += 1
            steps += 1
            total += reward
            for key, value in info.get("reward_components", {}).items():
                terms[key] += value
            if self.total_steps >= self.config.start_steps:
                losses = self.agent.update(self.buffer.sample(self.agent.config.batch_size))
            state = next_state
            if terminated or truncated:
                break
        reached = bool(info["goal_reached"])
        episode = self.buffer.end_episode()
        rewards = self.goal_reward.on_episode_end(self.buffer, episode, reached)
        groups = getattr(self.goal_reward, "last_groups", []) if reached else []
        outcome = "success" if reached else "collision" if info["collision"] else "timeout"
        self.outcomes.append(outcome)
        self.episode += 1
        return {
            "episode": self.episode, "return": round(float(np.sum(rewards)), 6),
            "steps": steps, "outcome": outcome,
            "success_rate_500": round(self.outcomes.count("success") / len(self.outcomes), 6),
            "collision_rate_500": round(self.outcomes.count("collision") / len(self.outcomes),
                                        6),
            "total_steps": self.total_steps, "losses": losses,
            "base_return": round(total, 6),
            **{f"r_{k}": round(v, 6) for k, v in terms.items()},
            "abr_patterns": len(getattr(self.goal_reward, "returns", [])),
            "abr_new_patterns": sum(g.new_pattern for g in groups),
            "abr_groups": len(groups),
        }

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
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(self.out / "tb"), purge_step=self.episode)
        new_file = not csv_path.exists()
        with csv_path.open("a", newline="") as f, tqdm(
            total=self.config.episodes, initial=self.episode, unit="ep", smoothing=0.05,
            desc=f"{self.config.algo}+{self.config.reward} {self.config.task}",
            disable=not self.config.progress,
        ) as bar:
            rows = csv.DictWriter(f, CSV_FIELDS, extrasaction="ignore")
            if new_file:
                rows.writeheader()
            t0, steps0, wall0 = time.perf_counter(), self.total_steps, self.wall_s
            while self.episode < self.config.episodes:
                row = self.run_episode()
                rows.writerow(row)
                for key in ("return", "steps", "success_rate_500", "collision_rate_500"):
                    writer.add_scalar(f"episode/{key}", row[key], self.episode)
                for key, value in row["losses"].items():
                    writer.add_scalar(f"loss/{key}", value, self.episode)
                elapsed = time.perf_counter() - t0
                self.wall_s = wall0 + elapsed
                rate = (self.total_steps - steps0) / max(elapsed, 1e-9)
                bar.set_postfix(success=f"{row['success_rate_500']:.0%}",
                                steps_s=f"{rate:.0f}", refresh=False)
                bar.update(1)
                if on_episode is not None:
                    on_episode({**row, "env_steps_per_s": rate, "wall_s": self.wall_s})
                if self.episode % self.config.checkpoint_every == 0:
                    f.flush()
                    self.save()
        self.save()
        writer.close()
        png = plot_runs([self.out], self.out / "curve.png")
        summary = {"episodes": self.episode, "total_steps": self.total_steps,
                   "success_rate_500": self.outcomes.count("success") / max(len(self.outcomes),
                                                                            1),
                   "wall_s": round(self.wall_s, 1), "curve": str(png), "checkpoint": str(ckpt)}
        (self.out / RESULT).write_text(json.dumps(summary, indent=2))
        return summary


def finished(out: Path, episodes: int) -> bool:
    """Whether the run in ``out`` has written its result for ``episodes`` episodes."""
    try:
        return json.loads((Path(out) / RESULT).read_text())["episodes"] >= episodes
    except (OSError, ValueError, KeyError, TypeError):
        return False


def _truncate_csv(path: Path, episodes: int) -> None:
    """Keep the header and the first ``episodes`` rows (those the checkpoint knows)."""
    if not path.exists():
        return
    lines = path.read_bytes().splitlines(keepends=True)  # bytes: keep csv's \r\n
    path.write_bytes(b"".join(lines[: 1 + episodes]))
