"""Where do the final actors time out, and what does waiting pay? (issue 10)

Flies each trial's final actor deterministically on the report's held-out episodes
(reset seeds 1,000,000,000 + i) and, for the episodes that time out, prints where the
vehicle ended (distance to the goal, the closest it came, altitude), how fast it moved
over the last 50 steps, and the base reward (eq. 3.5, the goal reward aside) it earned
per step over those 50 steps. With discount gamma, waiting forever at reward r a step
is worth r / (1 - gamma) to the critic, against TR's one-off +50 for arriving.

    python experiments/paper_dynamic/timeout_probe.py TRIAL_DIR [TRIAL_DIR ...] --episodes 100

With ``--family NAME --worlds N`` episode i flies held-out world i % N of that family
(as ``noise_probe.py``; issue 14's mixture policy on open worlds).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from policy.algorithms.rewards import RewardConfig, step_reward
from policy.training.evaluate import EVAL_SEED, env_for, make_controller
from sitl.world.families import eval_worlds

TAIL = 50  # steps at the end of a timeout that are summarised


def fly(trial: Path, episodes: int, family: str | None = None, worlds: int = 0) -> dict:
    config = json.loads((trial / "config.json").read_text())
    controller = make_controller(str(trial / "actor.pt"))
    names = eval_worlds(family, worlds) if family else []
    env = env_for(controller, names[0] if names else config["scenario"])
    reward_config = RewardConfig()
    outcomes, tails = {"success": 0, "collision": 0, "timeout": 0}, []
    for i in range(episodes):
        if names:
            env.sim.use_world(names[i % len(names)])
        state, _ = env.reset(seed=EVAL_SEED + i)
        dists, alts, rewards, speeds = [], [], [], []
        while True:
            state, _, terminated, truncated, info = env.step(controller(state))
            rec = info["record"]
            dists.append(rec.distance)
            alts.append(rec.altitude)
            rewards.append(step_reward(rec, reward_config)[0])
            speeds.append(float(np.linalg.norm(env.sim.vehicle.truth.velocity)))
            if terminated or truncated:
                outcome = rec.outcome or "timeout"
                outcomes[outcome] += 1
                if outcome == "timeout":
                    tails.append({"final_distance": dists[-1], "closest": min(dists),
                                  "altitude": float(np.mean(alts[-TAIL:])),
                                  "speed": float(np.mean(speeds[-TAIL:])),
                                  "reward_per_step": float(np.mean(rewards[-TAIL:]))})
                break
    env.close()
    out: dict = {"trial": trial.name, "family": family, "episodes": episodes,
                 **{k: v / episodes for k, v in outcomes.items()}}
    if tails:
        for key in tails[0]:
            values = np.array([t[key] for t in tails])
            out[f"timeout_{key}_median"] = round(float(np.median(values)), 3)
            out[f"timeout_{key}_p10_p90"] = [round(float(v), 3)
                                             for v in np.percentile(values, [10, 90])]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("trials", nargs="+", type=Path)
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--family", help="fly held-out worlds of this family instead")
    ap.add_argument("--worlds", type=int, default=20, help="with --family: how many")
    args = ap.parse_args()
    for trial in args.trials:
        print(json.dumps(fly(trial, args.episodes, args.family, args.worlds)), flush=True)


if __name__ == "__main__":
    main()
