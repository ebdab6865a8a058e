"""Probe (issue 9): what one TD3 update costs inside the trainer against the same update alone.

The bench_train rows time whole training loops; this times ``TD3.update`` itself, wrapped
with a clock, inside a real ``Trainer`` run (``bench_train``'s run: TD3+ABR on the valley,
5,000 env steps, the first 500 updates dropped) in the ``--sync`` or the default
(parallel) mode, and the same update alone (``alone``, on ``bench_td3``'s buffer).
``parts`` times each part of the update alone (medians of 500 mini-batches, 3 rounds): the
TD target (eqs. 2.11-2.12), the critic step (eq. 2.13: forward, backward, Adam), the
actor step (every ``policy_delay``-th update) and the soft target update. Run:

    python -m benchmarks.probe_update_cost {sync,parallel,alone,parts} [--precision bf16|fp32]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch

import policy.algorithms.td3 as td3
from benchmarks.bench_td3 import BATCH, _fill_ours
from benchmarks.bench_train import bench_config
from policy.algorithms.replay import Batch, ReplayBuffer
from policy.training.train import Trainer

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
            try:
                Trainer(bench_config(sync, precision=precision), Path(tmp)).run(
                    on_episode=on_episode)
            except _Done:
                pass
    finally:
        td3.TD3.update = update
    return durations[DROP:]


def alone(precision: str, n: int = 4000) -> list[float]:
    """Durations (s) of the same update on mini-batches of ``bench_td3``'s replay buffer
    (10,000 transitions of random observations, sampled as in training)."""
    torch.set_num_threads(1)
    agent = td3.TD3(td3.TD3Config(batch_size=BATCH, precision=precision))
    buf = _fill_ours(10_000)
    durations = []
    with td3.flush_denormals():
        for _ in range(n + DROP):
            batch = buf.sample(BATCH)
            t = time.perf_counter()
            agent.update(batch)  # the actor steps every policy_delay-th update, as in training
            durations.append(time.perf_counter() - t)
    return durations[DROP:]


def median_ms(buf: ReplayBuffer, f: Callable[[Batch], object], n: int = 600) -> float:
    """Median wall time (ms) of ``f`` on fresh mini-batches, the first 100 dropped."""
    times = []
    for _ in range(n):
        b = buf.sample(BATCH)
        t = time.perf_counter()
        f(b)
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times[100:])


def parts(precision: str) -> None:
    """Print what each part of an update costs, three rounds."""
    torch.set_num_threads(1)
    agent = td3.TD3(td3.TD3Config(batch_size=BATCH, precision=precision))
    buf = _fill_ours(10_000)

    def target(b: Batch) -> torch.Tensor:
        return agent.target(b.next_state, b.reward, b.done)

    calls = 0

    def target_as_in_updates(b: Batch) -> torch.Tensor:
        # an update refreshes the target networks' low-precision copies after every soft
        # update, i.e. before every policy_delay-th target
        nonlocal calls
        calls += 1
        if calls % agent.config.policy_delay == 0:
            agent.lp["actor_target"].changed()
            agent.lp["critic_target"].changed()
        return target(b)

    def actor_step_as_in_updates(b: Batch) -> float:
        agent.lp["critic"].changed()  # the critic has just stepped in a delayed update
        return agent.actor_step(b.state.to(agent.dtype))

    with td3.flush_denormals():
        for _ in range(300):
            agent.update(buf.sample(BATCH))
        for _ in range(3):
            tgt = median_ms(buf, target_as_in_updates)
            critic = median_ms(buf, lambda b: agent.learn(b, target(b), train_actor=False))
            critic -= median_ms(buf, target)
            actor = median_ms(buf, actor_step_as_in_updates)
            soft = median_ms(buf, lambda b: agent.update_targets())
            mean = tgt + critic + (actor + soft) / agent.config.policy_delay
            print(f"parts ({precision}): target {tgt:.2f} ms, critic step {critic:.2f}, actor "
                  f"step {actor:.2f}, soft update {soft:.2f}: {mean:.2f} ms an update on average",
                  flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("where", choices=["sync", "parallel", "alone", "parts"])
    parser.add_argument("--precision", default="bf16", choices=["bf16", "fp32"])
    args = parser.parse_args()
    if args.where == "parts":
        parts(args.precision)
        return
    d = (alone(args.precision) if args.where == "alone"
         else in_trainer(args.where == "sync", args.precision))
    q = statistics.quantiles(d, n=10)
    print(f"{args.where} ({args.precision}): {len(d)} updates, mean {1e3 * statistics.mean(d):.2f}"
          f" ms (critic-only and actor steps alternate: p10 {1e3 * q[0]:.2f}, "
          f"p90 {1e3 * q[-1]:.2f})")


if __name__ == "__main__":
    main()
