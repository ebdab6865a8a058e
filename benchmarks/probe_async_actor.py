"""Probe (issue 9): would an asynchronous actor step reach 1.7x ``--sync``?

``benchmarks/RESULTS.md`` (2026-12-07) bounds the default parallel mode at ~1.4x
``--sync`` while the whole TD3 update runs on the learner's core, and puts 1.7x within
reach only if the delayed actor step moves to the collector's core. This probe measures
that split before anyone builds it into the trainer. One harness, three modes, the same
work per env step (an env step of ``UavNavEnv`` on the valley with the actor acting, and
one bf16 TD3 update on ``bench_td3``'s replay buffer of random observations):

- ``sync``: one process, env step then the whole update (``TD3.update``), as ``--sync``;
- ``parallel``: the env in a collector process, the whole update in the learner, one update
  per env step and the collector at most ``MAX_LEAD`` steps ahead, as the default mode;
- ``async``: the learner does the TD target, the critic step and the soft target updates;
  the collector process also does the delayed actor step (every second env step, on the
  states of the learner's latest mini-batch, through a copy of the critic the learner
  publishes after each delayed step) and publishes its actor, which the learner's
  target policy follows. The critic the actor step uses is up to a few updates old:
  *not* TD3's synchronous delayed update, and this probe says nothing about learning.

Run (nothing else on the machine): ``python -m benchmarks.probe_async_actor [--steps N]``;
prints env steps/s per mode (interleaved, 3 repeats, medians) and the ratios.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from typing import Any

import numpy as np
import torch
import torch.multiprocessing as tmp

import policy.algorithms.td3 as td3
from benchmarks.bench_td3 import BATCH, _fill_ours
from policy.training.collector import SharedActor

MAX_LEAD = 8
WARMUP = 200


def _agent() -> td3.TD3:
    torch.set_num_threads(1)
    return td3.TD3(td3.TD3Config(batch_size=BATCH, precision="bf16"))


class _Env:
    """The valley env stepped with an agent's noisy actions (``TD3.act``), episodes reset
    in turn."""

    def __init__(self) -> None:
        from policy.training.env import UavNavEnv

        self.env, self.rng, self.episode = UavNavEnv(scenario="valley"), np.random.default_rng(0), 0
        self.state = self.env.reset(seed=0)[0]

    def step(self, agent: td3.TD3) -> None:
        action = agent.act(self.state, noise=True, rng=self.rng)
        self.state, _, terminated, truncated, _ = self.env.step(action)
        if terminated or truncated:
            self.episode += 1
            self.state = self.env.reset(seed=self.episode)[0]


def run_sync(steps: int) -> float:
    agent, buf, env = _agent(), _fill_ours(10_000), _Env()
    with td3.flush_denormals():
        for i in range(WARMUP + steps):
            if i == WARMUP:
                t0 = time.perf_counter()
            env.step(agent)
            agent.update(buf.sample(BATCH))
    return steps / (time.perf_counter() - t0)


def _collector(mode: str, steps: int, env_steps: Any, updates: Any, actor_pub: SharedActor,
               critic_pub: SharedActor, states: Any, states_version: Any) -> None:
    """The collector process: env steps (and, in ``async``, the delayed actor steps)."""
    agent, env = _agent(), _Env()
    seen_actor = seen_critic = seen_states = -1
    batch_states = states.clone()  # zeros until the learner's first delayed step
    with td3.flush_denormals():
        for i in range(WARMUP + steps):
            while i - updates.value > MAX_LEAD:  # bounded lead on the learner
                time.sleep(0.0001)
            if mode == "parallel":
                seen_actor = actor_pub.fetch(agent.actor, seen_actor)
            env.step(agent)
            env_steps.value = i + 1
            if mode == "async" and i % 2 == 1:  # the delayed actor step, here
                seen_critic = critic_pub.fetch(agent.critic, seen_critic)
                agent.lp["critic"].changed()
                v = states_version.value
                if v != seen_states and v % 2 == 0:  # a seqlock read, as SharedActor's
                    fresh = states.clone()
                    if states_version.value == v:
                        batch_states, seen_states = fresh, v
                agent.actor_step(batch_states.to(agent.dtype))
                actor_pub.publish(agent.actor)


def run_split(mode: str, steps: int) -> float:
    """``parallel`` or ``async``: env steps/s over ``steps`` after the warm-up."""
    ctx = tmp.get_context("spawn")
    agent, buf = _agent(), _fill_ours(10_000)
    actor_pub, critic_pub = SharedActor(agent.actor, ctx), SharedActor(agent.critic, ctx)
    actor_pub.publish(agent.actor)
    critic_pub.publish(agent.critic)
    env_steps, updates = ctx.Value("q", 0, lock=False), ctx.Value("q", 0, lock=False)
    states = torch.zeros(BATCH, agent.config.state_dim).share_memory_()
    states_version = ctx.Value("q", 0, lock=False)
    proc = ctx.Process(target=_collector, args=(mode, steps, env_steps, updates, actor_pub,
                                                critic_pub, states, states_version))
    proc.start()
    seen_actor = -1
    try:
        with td3.flush_denormals():
            for i in range(WARMUP + steps):
                if i == WARMUP:
                    t0 = time.perf_counter()
                while env_steps.value <= i:  # one update per env step received
                    if not proc.is_alive():
                        raise RuntimeError(f"collector died ({proc.exitcode})")
                    time.sleep(0.0001)
                batch = buf.sample(BATCH)
                if mode == "parallel":
                    agent.update(batch)
                    if agent.updates % 2 == 0:
                        actor_pub.publish(agent.actor)
                else:
                    seen_actor = actor_pub.fetch(agent.actor, seen_actor)
                    agent.lp["actor"].changed()
                    y = agent.target(batch.next_state, batch.reward, batch.done)
                    agent.learn(batch, y, train_actor=False)
                    if agent.delayed_step():
                        agent.update_targets()  # the actor target follows the collector's
                        critic_pub.publish(agent.critic)
                        states_version.value += 1
                        states.copy_(batch.state.reshape(BATCH, -1))
                        states_version.value += 1
                updates.value = agent.updates
            rate = steps / (time.perf_counter() - t0)
    finally:
        proc.join(timeout=30)
        if proc.is_alive():
            proc.kill()
    return rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    rates: dict[str, list[float]] = {"sync": [], "parallel": [], "async": []}
    for _ in range(args.repeats):
        for mode in rates:
            r = run_sync(args.steps) if mode == "sync" else run_split(mode, args.steps)
            rates[mode].append(r)
            print(f"{mode}: {r:.0f} env steps/s", flush=True)
    med = {m: statistics.median(v) for m, v in rates.items()}
    print(f"medians (pid {os.getpid()}): " + ", ".join(f"{m} {v:.0f}" for m, v in med.items())
          + f"; parallel / sync {med['parallel'] / med['sync']:.2f}x, async / sync "
          f"{med['async'] / med['sync']:.2f}x")


if __name__ == "__main__":
    main()
