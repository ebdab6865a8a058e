"""How many icosahedron faces are occupied per step, per world family (issue 14).

Flies the shipped valley policy on 15 validation worlds per family (``--steps`` steps of
each episode) and prints the mean, median and 90th percentile of occupied faces (face
value > 0) in the newest frame of the state.

    python experiments/general/occupied_faces.py [--worlds 15 --steps 60]
"""

from __future__ import annotations

import argparse

import numpy as np

from bus.task import TASK
from policy.training.env import UavNavEnv
from policy.training.evaluate import ActorController
from sitl.world.families import eval_worlds


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worlds", type=int, default=15)
    p.add_argument("--steps", type=int, default=60)
    args = p.parse_args()
    controller = ActorController("policy/shipped/td3_abr_valley/actor.pt")
    for family in ("valley", "city", "forest", "dynamic"):
        names = eval_worlds(family, args.worlds, validation=True)
        env = UavNavEnv(scenario=names[0])
        occupied = []
        for i, name in enumerate(names):
            env.sim.use_world(name)
            state, _ = env.reset(seed=5 + i)
            for _ in range(args.steps):
                faces = np.asarray(state).reshape(-1)[-TASK.obs_dim:][:TASK.faces]
                occupied.append(int((faces > 0).sum()))
                state, _, terminated, truncated, _ = env.step(controller(state))
                if terminated or truncated:
                    break
        env.close()
        print(f"{family}: occupied faces per step: mean {np.mean(occupied):.1f}, median "
              f"{np.median(occupied):.0f}, p90 {np.percentile(occupied, 90):.0f} "
              f"(of {TASK.faces}, {len(occupied)} steps)")


if __name__ == "__main__":
    main()
