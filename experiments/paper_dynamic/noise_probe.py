"""Do the final actors need exploration noise to reach the goal? (issue 10, the timeouts)

Flies a trial's final actor on the held-out episodes of the report (reset seeds
1,000,000,000 + i) once deterministically, as `skyloop experiment report` does, and once
with the training's exploration noise added to every action (N(0, 0.2), clipped to the
action bound: TD3Config.exploration_noise), and prints the outcomes of both.

    python experiments/paper_dynamic/noise_probe.py TRIAL_DIR [TRIAL_DIR ...] --episodes 100

With ``--family NAME --worlds N`` episode i flies held-out world i % N of that family
(``sitl.world.families.eval_worlds``, as ``skyloop eval --scenario family:NAME --worlds N``)
instead of the trial's own scenario (issue 14's mixture policy on open worlds).
"""

from __future__ import annotations

import argparse
import collections
import json
from pathlib import Path

import numpy as np

from policy.algorithms.td3 import TD3Config, explore
from policy.training.evaluate import EVAL_SEED, env_for, make_controller
from sitl.world.families import eval_worlds


def fly(trial: Path, episodes: int, sigma: float, family: str | None = None,
        worlds: int = 0) -> dict[str, float]:
    config = json.loads((trial / "config.json").read_text())
    controller = make_controller(str(trial / "actor.pt"))
    names = eval_worlds(family, worlds) if family else []
    env = env_for(controller, names[0] if names else config["scenario"])
    rng = np.random.default_rng(0)
    bound = TD3Config().max_action
    outcomes: collections.Counter[str] = collections.Counter()
    for i in range(episodes):
        if names:
            env.sim.use_world(names[i % len(names)])
        state, _ = env.reset(seed=EVAL_SEED + i)
        while True:
            action = controller(state)
            if sigma > 0:
                action = explore(action, rng, sigma, bound)
            state, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                record = info["record"]
                outcomes[record.outcome or "timeout"] += 1
                break
    env.close()
    return {k: outcomes[k] / episodes for k in ("success", "collision", "timeout")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="+", type=Path)
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--sigma", type=float, default=TD3Config().exploration_noise)
    ap.add_argument("--family", help="fly held-out worlds of this family instead")
    ap.add_argument("--worlds", type=int, default=20, help="with --family: how many")
    args = ap.parse_args()
    for trial in args.trials:
        for sigma in (0.0, args.sigma):
            print(json.dumps({"trial": trial.name, "sigma": sigma, "family": args.family,
                              **fly(trial, args.episodes, sigma, args.family, args.worlds)}),
                  flush=True)


if __name__ == "__main__":
    main()
