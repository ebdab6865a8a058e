"""Training throughput: env steps per second of whole TD3+ABR training runs on the valley.

Six rows in the same run, the same env, network sizes (400-300), batch (100) and one
gradient step per env step after the same warm-up:

- ``train_env_steps_per_s``: ``skyloop train`` as it runs by default (a collector process
  beside the learner, ``policy.training.collector``);
- ``train_pipeline_target_env_steps_per_s``: the same with ``--pipeline target`` (a
  second learner thread for the TD targets, ``policy.algorithms.pipeline``; the default,
  ``off``, is one thread: faster in 3 of 4 runs on two machines, ``RESULTS.md``);
- ``train_fp32_env_steps_per_s``: the default with ``--precision fp32`` (the default is
  "auto": bfloat16 matmuls where the CPU has bfloat16 units; ``precision`` says which it
  took here);
- ``train_sync_env_steps_per_s``: ``skyloop train --sync`` (env and learner in turn);
- ``train_sync_fp32_env_steps_per_s``: ``--sync --precision fp32`` (the peer of the fp32
  row: ``speedup_fp32_vs_sync_fp32`` compares like with like in float32);
- ``sb3_train_env_steps_per_s``: Stable-Baselines3's ``TD3.learn()`` on the same env
  (``train_freq=1, gradient_steps=1``), with denormals flushed as in our trainer
  (``policy.algorithms.td3.flush_denormals``) so that both get the same machine setting.

Each row times ``steps`` env steps after ``warmup`` steps (random actions, no updates,
then a few hundred updated steps so every loop is at speed); the rows are interleaved
``repeats`` times and the medians are reported, so load from other processes hits all
alike. Also the collector's own rate (env steps/s of ``Collector.round`` with the actor
acting, no learner) for 1 and 4 envs in one process: the ceiling of the parallel mode;
with the shipped actor (headline rows) and with seeded random actors (``_collector``).

Run: ``python -m benchmarks.bench_train [--quick] [--collector-only] [--json out.json]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from policy.algorithms.td3 import explore, flush_denormals
from policy.training.collector import Collector
from policy.training.env import UavNavEnv
from policy.training.train import TrainConfig, Trainer, episode_seed, resolve_precision

START, SETTLE = 1000, 300  # random steps before updates; updated steps before timing


class _Done(Exception):
    """Raised from the episode callback once enough steps are timed."""


def bench_config(sync: bool, seed: int = 0, threads: int = 1, precision: str | None = None,
                 pipeline: str | None = None) -> TrainConfig:
    """The training run every row times: TD3+ABR on the valley, START random steps, no
    checkpoints, no end (``precision``/``pipeline`` None: ``TrainConfig``'s default)."""
    return TrainConfig(algo="td3", reward="abr", scenario="valley", episodes=10**6,
                       seed=seed, start_steps=START, buffer_size=100_000,
                       checkpoint_every=10**6, sync=sync, threads=threads, progress=False,
                       **({} if precision is None else {"precision": precision}),
                       **({} if pipeline is None else {"pipeline": pipeline}))


def _ours(sync: bool, steps: int, threads: int, seed: int, precision: str | None = None,
          pipeline: str | None = None) -> float:
    """Env steps/s of a Trainer run between SETTLE and SETTLE + steps updated steps
    (``precision`` None: ``TrainConfig``'s default)."""
    marks: list[tuple[float, int]] = []

    def on_episode(row: dict) -> None:
        marks.append((time.perf_counter(), row["total_steps"]))
        if row["total_steps"] >= START + SETTLE + steps:
            raise _Done

    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as tmp:
        cfg = bench_config(sync, seed, threads, precision, pipeline)
        try:
            Trainer(cfg, Path(tmp)).run(on_episode=on_episode)
        except _Done:
            pass
    first = next(m for m in marks if m[1] >= START + SETTLE)
    last = marks[-1]
    return (last[1] - first[1]) / (last[0] - first[0])


def _sb3(steps: int, seed: int) -> float | None:
    try:
        from stable_baselines3 import TD3 as SB3TD3
        from stable_baselines3.common.callbacks import BaseCallback
        from stable_baselines3.common.noise import NormalActionNoise
    except ImportError:
        return None
    marks: dict[str, tuple[float, int]] = {}

    class _Clock(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps == START + SETTLE:
                marks["first"] = (time.perf_counter(), self.num_timesteps)
            marks["last"] = (time.perf_counter(), self.num_timesteps)
            return True

    env = UavNavEnv(scenario="valley")
    model = SB3TD3(
        "MlpPolicy", env, policy_kwargs={"net_arch": [400, 300]}, batch_size=100,
        buffer_size=100_000, learning_starts=START, learning_rate=1e-3, tau=0.005,
        gamma=0.99, policy_delay=2, target_policy_noise=0.4, target_noise_clip=0.5,
        train_freq=1, gradient_steps=1, action_noise=NormalActionNoise(np.zeros(4),
                                                                        0.2 * np.ones(4)),
        device="cpu", seed=seed, verbose=0)
    with flush_denormals():  # the setting our trainer runs with (policy.algorithms.td3)
        model.learn(total_timesteps=START + SETTLE + steps, callback=_Clock())
    (t0, s0), (t1, s1) = marks["first"], marks["last"]
    return (s1 - s0) / (t1 - t0)


def _collector(n_envs: int, steps: int, actor: str = "shipped", seed: int = 0) -> float:
    """Env steps/s of the collector alone (actor + noise acting, no learner).

    ``actor="shipped"``: the shipped valley actor, a policy that flies, as the collector
    runs for most of a training run; ``"random"``: a freshly initialised actor (seeded
    with ``seed``), as at the start of one. The rate follows the states the actor flies
    into: the LiDAR's terrain cast is most of a step and costs 0.28-0.58 ms a scan
    between random actors (0.36 with the shipped one; 0.03 under uniform random actions,
    which keep the vehicle level near its start). An unseeded random actor, as this row
    used before, made it swing 750-1,750 between runs.
    """
    from policy.algorithms.networks import Actor
    from policy.algorithms.td3 import load_actor
    from policy.shipped import SHIPPED_POLICY

    if actor == "shipped":
        net = load_actor(SHIPPED_POLICY)
    else:
        torch.manual_seed(seed)
        net = Actor()
    net.requires_grad_(False)

    def act(states: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        with torch.no_grad():
            a = net(torch.as_tensor(states).reshape(len(states), -1)).numpy()
        return explore(a, rng, 0.2, 2.0)

    envs = [UavNavEnv(scenario="valley") for _ in range(n_envs)]
    c = Collector(envs, partial(episode_seed, seed), np.random.default_rng(seed), 2.0, 4,
                  start_steps=0)
    for _ in range(max(1, 100 // n_envs)):
        c.round(act)
    t0, s0 = time.perf_counter(), c.steps
    while c.steps - s0 < steps:
        c.round(act)
    return (c.steps - s0) / (time.perf_counter() - t0)


def collector_rows(steps: int, repeats: int) -> dict[str, Any]:
    """The collector alone: 1 and 4 envs with the shipped actor, and 1 env with random
    actors (seeds 0..repeats-1), interleaved; medians. One torch thread (a collector's)."""
    torch.set_num_threads(1)
    runs: dict[str, list[float]] = {"shipped_1env": [], "shipped_4envs": [], "random_1env": []}
    for r in range(repeats):
        runs["shipped_1env"].append(_collector(1, steps, "shipped", seed=r))
        runs["shipped_4envs"].append(_collector(4, steps, "shipped", seed=r))
        runs["random_1env"].append(_collector(1, steps, "random", seed=r))
    return {"collector_env_steps_per_s": statistics.median(runs["shipped_1env"]),
            "collector_4envs_env_steps_per_s": statistics.median(runs["shipped_4envs"]),
            "collector_random_actor_env_steps_per_s": statistics.median(runs["random_1env"]),
            "collector_runs": runs}


def sizes(quick: bool) -> tuple[int, int]:
    """(timed env steps a training row, repeats); the collector rows time at most 2,000."""
    return (600, 1) if quick else (3000, 3)


def run(quick: bool = False, threads: int = 1) -> dict[str, Any]:
    steps, repeats = sizes(quick)
    rows: dict[str, list[float]] = {"parallel": [], "parallel_target": [],
                                    "parallel_fp32": [], "sync": [], "sync_fp32": [],
                                    "sb3": []}
    torch.set_num_threads(1)
    for r in range(repeats):
        rows["parallel"].append(_ours(False, steps, threads, seed=r))
        rows["parallel_target"].append(_ours(False, steps, threads, seed=r,
                                             pipeline="target"))
        rows["parallel_fp32"].append(_ours(False, steps, threads, seed=r, precision="fp32"))
        rows["sync"].append(_ours(True, steps, 1, seed=r))
        rows["sync_fp32"].append(_ours(True, steps, 1, seed=r, precision="fp32"))
        sb3 = _sb3(steps, seed=r)
        if sb3 is not None:
            rows["sb3"].append(sb3)
    med = {k: statistics.median(v) for k, v in rows.items() if v}
    out: dict[str, Any] = {
        "train_env_steps_per_s": med["parallel"],
        "train_pipeline_target_env_steps_per_s": med["parallel_target"],
        "train_fp32_env_steps_per_s": med["parallel_fp32"],
        "train_sync_env_steps_per_s": med["sync"],
        "train_sync_fp32_env_steps_per_s": med["sync_fp32"],
        "speedup_vs_sync": med["parallel"] / med["sync"],
        "speedup_fp32_vs_sync_fp32": med["parallel_fp32"] / med["sync_fp32"],
        "precision": resolve_precision(TrainConfig.precision, "cpu"),
        **collector_rows(min(steps, 2000), repeats),
        "config": {"steps_timed": steps, "warmup_random": START, "warmup_updated": SETTLE,
                   "repeats": repeats, "learner_threads": threads, "sync_threads": 1,
                   "precision": f"{TrainConfig.precision} (the default; fp32 rows: "
                                "--precision fp32)",
                   "flush_denormals": True,
                   "hidden": [400, 300], "batch": 100, "torch": torch.__version__},
        "runs": rows, "peers": {},
    }
    if "sb3" in med:
        import stable_baselines3

        out["sb3_train_env_steps_per_s"] = med["sb3"]
        out["speedup_vs_sb3"] = med["parallel"] / med["sb3"]
        out["peers"]["stable_baselines3_td3_learn"] = {
            "version": stable_baselines3.__version__, "env_steps_per_s": med["sb3"]}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--threads", type=int, default=1, help="the learner's torch threads")
    ap.add_argument("--collector-only", action="store_true",
                    help="only the collector rows (a minute; no training)")
    ap.add_argument("--json")
    args = ap.parse_args()
    steps, repeats = sizes(args.quick)
    out = (collector_rows(min(steps, 2000), repeats) if args.collector_only
           else run(args.quick, args.threads))
    print(json.dumps(out, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
