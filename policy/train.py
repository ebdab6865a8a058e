"""Training: TD3 or DDPG with a goal-reward variant, in the in-process env (Algorithm 3.1).

``skyloop train --algo td3 --reward abr --scenario valley --episodes 5000 --seed 0 --out DIR``

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
ACTOR = "actor.pt"
CSV_FIELDS = ["episode", "return", "steps", "outcome", "success_rate_500",
              "collision_rate_500", "total_steps"]
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
    extra: dict = field(default_factory=dict)

    def validate(self) -> None:
        from sitl.world import load_scenario  # raises ScenarioError naming the scenario

        if self.algo not in ALGOS:
            raise ValueError(f"unknown algorithm {self.algo!r}; choose from {sorted(ALGOS)}")
        if self.reward not in GOAL_REWARDS:
            raise ValueError(f"unknown reward {self.reward!r}; choose from {sorted(GOAL_REWARDS)}")
        if self.episodes < 1:
            raise ValueError(f"--episodes must be >= 1, got {self.episodes}")
        load_scenario(self.scenario)


def episode_seed(seed: int, episode: int) -> int:
    return seed * 1_000_003 + episode


class Trainer:
    """Owns everything a checkpoint must hold; ``run`` is the loop of Algorithm 3.1."""

    def __init__(self, config: TrainConfig, out: Path) -> None:
        config.validate()
        self.config, self.out = config, Path(out)
        torch.set_num_threads(config.threads)
        torch.manual_seed(config.seed)
        self.env = UavNavEnv(scenario=config.scenario, lidar_max_range=config.lidar_max_range)
        self.agent = make_agent(config.algo, seed=config.seed)
        self.buffer = ReplayBuffer(config.buffer_size, (3, 35), 4, seed=config.seed)
        self.goal_reward = make_goal_reward(config.reward, RewardConfig(), seed=config.seed)
        self.rng = np.random.default_rng(config.seed)
        self.episode = 0
        self.total_steps = 0
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
        for key in ("algo", "reward", "scenario", "seed"):
            if saved[key] != getattr(self.config, key):
                raise ValueError(f"{path}: checkpoint has {key}={saved[key]!r} but this run "
                                 f"asks for {getattr(self.config, key)!r}")
        self.agent.load_state_dict(state["agent"])
        self.buffer.load_state_dict(state["buffer"])
        self.goal_reward.load_state_dict(state["goal_reward"])
        self.rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        self.episode, self.total_steps = state["episode"], state["total_steps"]
        self.outcomes = deque(state["outcomes"], maxlen=WINDOW)

    # -- the loop ------------------------------------------------------------------

    def act(self, state: np.ndarray) -> np.ndarray:
        if self.total_steps < self.config.start_steps:
            return self.rng.uniform(-2.0, 2.0, 4).astype(np.float32)
        return self.agent.act(state, noise=True, rng=self.rng)

    def run_episode(self) -> dict:
        state, _ = self.env.reset(seed=episode_seed(self.config.seed, self.episode))
        total, steps, losses = 0.0, 0, {}
        while True:
            action = self.act(state)
            next_state, reward, terminated, truncated, info = self.env.step(action)
            self.buffer.add(state, action, reward, next_state, terminated)
            self.total_steps += 1
            steps += 1
            total += reward
            if self.total_steps >= self.config.start_steps:
                losses = self.agent.update(self.buffer.sample(self.agent.config.batch_size))
            state = next_state
            if terminated or truncated:
                break
        reached = bool(info["goal_reached"])
        episode = self.buffer.end_episode()
        rewards = self.goal_reward.on_episode_end(self.buffer, episode, reached)
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
        }

    def run(self, resume: bool = False) -> dict:
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
            desc=f"{self.config.algo}+{self.config.reward} {self.config.scenario}",
        ) as bar:
            rows = csv.DictWriter(f, CSV_FIELDS, extrasaction="ignore")
            if new_file:
                rows.writeheader()
            t0, steps0 = time.perf_counter(), self.total_steps
            while self.episode < self.config.episodes:
                row = self.run_episode()
                rows.writerow(row)
                for key in ("return", "steps", "success_rate_500", "collision_rate_500"):
                    writer.add_scalar(f"episode/{key}", row[key], self.episode)
                for key, value in row["losses"].items():
                    writer.add_scalar(f"loss/{key}", value, self.episode)
                rate = (self.total_steps - steps0) / max(time.perf_counter() - t0, 1e-9)
                bar.set_postfix(success=f"{row['success_rate_500']:.0%}",
                                steps_s=f"{rate:.0f}", refresh=False)
                bar.update(1)
                if self.episode % self.config.checkpoint_every == 0:
                    f.flush()
                    self.save()
        self.save()
        writer.close()
        png = plot_runs([self.out], self.out / "curve.png")
        return {"episodes": self.episode, "total_steps": self.total_steps,
                "success_rate_500": self.outcomes.count("success") / max(len(self.outcomes), 1),
                "curve": str(png), "checkpoint": str(ckpt)}


def _truncate_csv(path: Path, episodes: int) -> None:
    """Keep the header and the first ``episodes`` rows (those the checkpoint knows)."""
    if not path.exists():
        return
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines[: 1 + episodes]))
