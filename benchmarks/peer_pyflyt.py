"""Peer benchmark: PyFlyt's QuadX-Waypoints env steps/s (no LiDAR), run in its own venv.

PyFlyt pins numpy < 2, so it lives in ``.venv-peers`` (made by ``make bench``) and this
script runs there as a subprocess, printing one JSON line. Random actions, the env's
default settings, the same step-counting as ``bench_env``.
"""

from __future__ import annotations

import json
import statistics
import sys
import time

import gymnasium
import PyFlyt.gym_envs  # noqa: F401  (registers the envs)


def main(steps: int, repeats: int) -> None:
    env = gymnasium.make("PyFlyt/QuadX-Waypoints-v4")
    env.reset(seed=0)
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            _, _, term, trunc, _ = env.step(env.action_space.sample())
            if term or trunc:
                env.reset()
        rates.append(steps / (time.perf_counter() - t0))
    env.close()
    print(json.dumps({"pyflyt_quadx_waypoints_steps_per_s": statistics.median(rates)}))


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]))
