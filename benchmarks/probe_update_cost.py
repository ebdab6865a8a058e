"""Probe (issue 9): what one TD3 update costs inside the trainer against the same update alone.

The bench_train rows time whole training loops; this times ``TD3.update`` itself, wrapped
with a clock, inside a real ``Trainer`` run (TD3+ABR on the valley, 5,000 env steps, the
first 500 updates dropped) in the ``--sync`` or the default (parallel) mode, and then the
same agent configuration alone on random mini-batches (``alone``). Run:

    python -m benchmarks.probe_update_cost {sync,parallel,alone} [--precision bf16|fp32]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

import policy.algorithms.td3 as td3
from policy.algorithms.replay import Batch
from policy.training.train import TrainConfig, Trainer

STEPS, DROP = 5000, 500


class _Done(Exception):
    pass


def in_trainer(sync: bool, precision: str) -> list[float]:
    """Durations (s) of every TD3.update of a short Trainer run."""
    durations: list[float] = []
    update = td3.TD3.update

    def timed(self: td3.TD3, *args: object, **kwargs: object) -> dict[str, float]:
        t = time.perf_counter()
        out = update(self, *args, **kwargs)
        durations.append(time.perf_counter() - t)
        return out

    def on_episode(row: dict) -> None:
        if row["total_steps"] >= STEPS:
            raise _Done

    td3.TD3.update = timed
    try:
        with tempfile.TemporaryDirectory() as tmp:
            cfg = TrainConfig(algo="td3", reward="abr", scenario="valley", episodes=10**6,
                              start_steps=1000, buffer_size=100_000, checkpoint_every=10**6,
                              sync=sync, precision=precision, progress=False)
            try:
                Trainer(cfg, Path(tmp)).run(on_episode=on_episode)
            except _Done:
                pass
    finally:
        td3.TD3.update = update
    return durations[DROP:]


def alone(precision: str, n: int = 4000) -> list[float]:
    """Durations (s) of the same update on random mini-batches from a 100,000-row table."""
    torch.set_num_threads(1)
    cfg = TrainConfig(precision=precision)
    agent = td3.TD3(td3.TD3Config(precision=cfg.precision))
    rows, b = 100_000, agent.config.batch_size
    s = torch.rand(rows, agent.config.state_dim) * 2 - 1
    a = (torch.rand(rows, agent.config.action_dim) * 2 - 1) * agent.config.max_action
    r = torch.randn(rows, 1)
    durations = []
    with td3.flush_denormals():
        for _ in range(n + DROP):
            idx = torch.randint(0, rows - 1, (b,))
            batch = Batch(s[idx], a[idx], r[idx], s[idx + 1], torch.zeros(b, 1))
            t = time.perf_counter()
            agent.update(batch)  # the actor steps every policy_delay-th update, as in training
            durations.append(time.perf_counter() - t)
    return durations[DROP:]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("where", choices=["sync", "parallel", "alone"])
    parser.add_argument("--precision", default="bf16", choices=["bf16", "fp32"])
    args = parser.parse_args()
    d = (alone(args.precision) if args.where == "alone"
         else in_trainer(args.where == "sync", args.precision))
    q = statistics.quantiles(d, n=10)
    print(f"{args.where} ({args.precision}): {len(d)} updates, mean {1e3 * statistics.mean(d):.2f}"
          f" ms (critic-only and actor steps alternate: p10 {1e3 * q[0]:.2f}, "
          f"p90 {1e3 * q[-1]:.2f})")


if __name__ == "__main__":
    main()
