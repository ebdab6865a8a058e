"""TD3 gradient updates per second: ours vs Stable-Baselines3, side by side.

Sizes are the paper's: actor and critics 400-300, batch 100, state 105 (3 x 35),
action 4; one thread (``torch.set_num_threads(1)``). One "update" is one gradient step
including the replay sample (TD3's policy delay 2 means every second step also updates
the actor and the targets), for both implementations. Blocks of ours and SB3's are
interleaved and each is timed several times; the medians are reported, so load from
other processes hits both alike.

Run: ``python -m benchmarks.bench_td3 [--quick] [--json out.json]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from policy.algorithms.replay import ReplayBuffer
from policy.algorithms.td3 import TD3, TD3Config

STATE_DIM, ACTION_DIM, MAX_ACTION, BATCH, HIDDEN = 105, 4, 2.0, 100, (400, 300)


def _fill_ours(n: int, seed: int = 0) -> ReplayBuffer:
    """``n`` transitions of 300-step episodes of random observations, as frame stacks."""
    rng = np.random.default_rng(seed)
    buf = ReplayBuffer(capacity=n, state_shape=(3, 35), action_dim=ACTION_DIM, seed=seed)
    obs = rng.normal(size=(n + 1, 35)).astype(np.float32)
    actions = rng.uniform(-MAX_ACTION, MAX_ACTION, (n, ACTION_DIM)).astype(np.float32)
    rewards = rng.normal(size=n).astype(np.float32)
    state = np.zeros((3, 35), np.float32)
    state[-1] = obs[0]
    for i in range(n):
        next_state = np.concatenate([state[1:], obs[i + 1 : i + 2]])
        buf.add(state, actions[i], float(rewards[i]), next_state, i % 300 == 299)
        state = next_state
        if i % 300 == 299:
            buf.end_episode()
            state = np.zeros((3, 35), np.float32)
            state[-1] = obs[i + 1]
    return buf


def _ours() -> Callable[[int], None]:
    agent = TD3(TD3Config(batch_size=BATCH))
    buf = _fill_ours(10_000)

    def steps(n: int) -> None:
        for _ in range(n):
            agent.update(buf.sample(BATCH))

    return steps


def _sb3() -> Callable[[int], None] | None:
    try:
        import gymnasium as gym
        from stable_baselines3 import TD3 as SB3TD3
        from stable_baselines3.common.logger import configure
    except ImportError:
        return None

    class _Env(gym.Env):
        observation_space = gym.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32)
        action_space = gym.spaces.Box(-MAX_ACTION, MAX_ACTION, (ACTION_DIM,), np.float32)

        def reset(self, seed=None, options=None):
            return np.zeros(STATE_DIM, np.float32), {}

        def step(self, action):
            return np.zeros(STATE_DIM, np.float32), 0.0, False, False, {}

    n = 10_000
    model = SB3TD3(
        "MlpPolicy", _Env(), policy_kwargs={"net_arch": list(HIDDEN)}, batch_size=BATCH,
        buffer_size=n, learning_starts=0, learning_rate=1e-3, tau=0.005, gamma=0.99,
        policy_delay=2, target_policy_noise=0.2 * MAX_ACTION, target_noise_clip=0.5,
        device="cpu", seed=0, verbose=0,
    )
    model.set_logger(configure(None, []))
    rb = model.replay_buffer
    rng = np.random.default_rng(0)
    rb.observations[:n] = rng.normal(size=rb.observations[:n].shape)
    rb.next_observations[:n] = rng.normal(size=rb.next_observations[:n].shape)
    rb.actions[:n] = rng.uniform(-1, 1, rb.actions[:n].shape)  # SB3 stores scaled actions
    rb.rewards[:n] = rng.normal(size=rb.rewards[:n].shape)
    rb.full = True

    def steps(k: int) -> None:
        model.train(gradient_steps=k, batch_size=BATCH)

    return steps


def _time(fn: Callable[[int], None], n: int) -> tuple[float, float]:
    """(wall-clock, thread-CPU) updates per second of one block of ``n`` updates."""
    w0, c0 = time.perf_counter(), time.thread_time()
    fn(n)
    w1, c1 = time.perf_counter(), time.thread_time()
    return n / (w1 - w0), n / max(c1 - c0, 1e-9)


def run(quick: bool = False) -> dict[str, Any]:
    """Measure; returns ``td3_updates_per_s`` and, when SB3 is importable,
    ``sb3_td3_updates_per_s`` (also under ``peers``) and the ratio."""
    torch.set_num_threads(1)
    n_block, repeats, warmup = (100, 3, 20) if quick else (300, 7, 50)
    impls: dict[str, Callable[[int], None]] = {"ours": _ours()}
    sb3 = _sb3()
    if sb3 is not None:
        impls["sb3"] = sb3
    for fn in impls.values():
        fn(warmup)
    wall: dict[str, list[float]] = {k: [] for k in impls}
    cpu: dict[str, list[float]] = {k: [] for k in impls}
    for _ in range(repeats):
        for name, fn in impls.items():  # interleaved blocks
            w, c = _time(fn, n_block)
            wall[name].append(w)
            cpu[name].append(c)
    med = {k: statistics.median(v) for k, v in wall.items()}
    med_cpu = {k: statistics.median(v) for k, v in cpu.items()}
    out: dict[str, Any] = {
        "td3_updates_per_s": med["ours"],
        "td3_updates_per_cpu_s": med_cpu["ours"],
        "config": {"hidden": list(HIDDEN), "batch": BATCH, "state_dim": STATE_DIM,
                   "action_dim": ACTION_DIM, "threads": 1, "block": n_block,
                   "repeats": repeats, "torch": torch.__version__},
        "peers": {},
    }
    if "sb3" in med:
        import stable_baselines3

        out["sb3_td3_updates_per_s"] = med["sb3"]
        out["speedup_vs_sb3"] = med["ours"] / med["sb3"]
        out["speedup_vs_sb3_cpu_time"] = med_cpu["ours"] / med_cpu["sb3"]
        out["peers"]["stable_baselines3_td3"] = {
            "version": stable_baselines3.__version__,
            "updates_per_s": med["sb3"],
            "updates_per_cpu_s": med_cpu["sb3"],
        }
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", default=None, help="write the results here")
    args = ap.parse_args(argv)
    res = run(quick=args.quick)
    rows = [(k, v) for k, v in res.items() if isinstance(v, int | float)]
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k:<{width}}  {v:10.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=2)


if __name__ == "__main__":
    main()
