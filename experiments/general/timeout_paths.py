"""Top views of a policy's timed-out episodes on held-out worlds of a family (issue 14).

Flies the actor deterministically on held-out world i % N of the family (reset seeds
1,000,000,000 + i, as ``skyloop eval --scenario family:NAME --worlds N``) and draws the
first ``--show`` timeouts over the world's terrain (height as colour), with start,
goal and the 2 m goal circle; a line per timeout on stdout (closest approach, mean
altitude).

    python experiments/general/timeout_paths.py ACTOR --family valley --worlds 20 --out FIG.png
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from policy.training.evaluate import EVAL_SEED, env_for, make_controller  # noqa: E402
from sitl.world.families import eval_worlds  # noqa: E402


def fly_episode(env, controller, world: str, i: int) -> str:
    """Episode ``i`` deterministically on ``world`` (reset seed 1,000,000,000 + i, as
    ``skyloop eval``); its outcome. The path stays in ``env.path``."""
    env.sim.use_world(world)
    state, _ = env.reset(seed=EVAL_SEED + i)
    while True:
        state, _, terminated, truncated, info = env.step(controller(state))
        if terminated or truncated:
            return info["record"].outcome or "timeout"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("actor", type=Path)
    ap.add_argument("--family", required=True)
    ap.add_argument("--worlds", type=int, default=20)
    ap.add_argument("--episodes", type=int, default=60, help="at most this many flown")
    ap.add_argument("--show", type=int, default=6, help="timeouts drawn")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    controller = make_controller(str(args.actor))
    names = eval_worlds(args.family, args.worlds)
    env = env_for(controller, names[0])
    shown = []
    for i in range(args.episodes):
        if fly_episode(env, controller, names[i % len(names)], i) != "timeout":
            continue
        path, goal, world = np.array(env.path), env.sim.goal.copy(), env.sim.world
        d = np.linalg.norm(path - goal, axis=1)
        print(f"episode {i} world {names[i % len(names)]}: closest {d.min():.1f} m, "
              f"final {d[-1]:.1f} m, mean altitude {path[:, 2].mean():.1f} m", flush=True)
        shown.append((i, path, goal, world))
        if len(shown) == args.show:
            break
    env.close()
    cols = min(3, max(1, len(shown)))
    rows = max(1, math.ceil(len(shown) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 5 * rows), squeeze=False)
    for ax, (i, path, goal, world) in zip(axes.flat, shown, strict=False):
        t = world.terrain
        xmin, xmax, ymin, ymax = t.extent
        im = ax.imshow(t.heights, origin="lower", extent=(xmin, xmax, ymin, ymax),
                       cmap="terrain")
        for solid in getattr(world, "solids", []):
            v = np.asarray(solid.vertices)
            ax.fill(v[:, 0], v[:, 1], color="k", alpha=0.25, lw=0)
        ax.plot(path[:, 0], path[:, 1], "r-", lw=1)
        ax.plot(*path[0, :2], "go", label="start")
        ax.plot(*goal[:2], "b*", ms=12, label="goal")
        ax.add_patch(plt.Circle(goal[:2], 2.0, fill=False, color="b"))
        ax.set_title(f"held-out episode {i}: timeout", fontsize=9)
        fig.colorbar(im, ax=ax, shrink=0.7, label="terrain height (m)")
    for ax in list(axes.flat)[len(shown):]:
        ax.axis("off")
    if shown:
        axes.flat[0].legend(loc="upper right", fontsize=8)
    fig.suptitle(f"{args.actor.parent.name}: timeouts on held-out {args.family} worlds")
    fig.tight_layout()
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
