"""Over or around? How high policies fly in each family, and whether they cross the hills
and ridges or go round them (issue 14: is the mixture policy's open-world loss a habit
learned in the streets?).

Flies each actor deterministically on validation worlds of each family (episode i on
world i % N, reset seeds 1,000,000,000 + i, as ``skyloop eval --scenario family:NAME
--worlds N --validation``) and records per episode its outcome, its highest altitude,
and whether it flew *over* raised terrain: the highest ground it passed over (terrain
height under the vehicle, buildings and trees aside) above the flight level + 1 m, that
is over a hill's or ridge's flank the flight level would have hit. A table per actor
and family on stdout and in ``--json``; a figure of the highest altitude per episode.

    python experiments/general/altitude_probe.py valley=shipped:valley \
        mixture=experiments/general_mix/.../snapshots/actor-ep900.pt --worlds 20 --episodes 40 \
        --json OUT.json --out FIG.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from timeout_paths import fly_episode

from policy.training.evaluate import env_for, make_controller
from sitl.world.families import eval_worlds

FAMILIES = ("valley", "dynamic", "forest", "city")
OVER = 1.0  # m above the flight level: ground higher than this under the path is "over"


def fly(actor: str, family: str, worlds: int, episodes: int) -> list[dict]:
    """One row per episode: outcome, highest altitude, highest ground passed over."""
    controller = make_controller(actor, task=None)
    names = eval_worlds(family, worlds, validation=True)
    env = env_for(controller, names[0])
    rows = []
    for i in range(episodes):
        outcome = fly_episode(env, controller, names[i % len(names)], i)
        path = np.array(env.path)
        ground = np.asarray(env.sim.world.terrain_height(path[:, 0], path[:, 1]))
        rows.append({"episode": i, "outcome": outcome,
                     "max_altitude": float(path[:, 2].max()),
                     "max_ground_under": float(ground.max())})
    env.close()
    return rows


def summary(rows: list[dict], flight_level: float) -> dict:
    """Rates and medians of one actor's rows in one family."""
    n = len(rows)
    over = [r["max_ground_under"] > flight_level + OVER for r in rows]
    return {"episodes": n,
            "success": sum(r["outcome"] == "success" for r in rows) / n,
            "timeout": sum(r["outcome"] == "timeout" for r in rows) / n,
            "max_altitude_median": float(np.median([r["max_altitude"] for r in rows])),
            "above_6m": sum(r["max_altitude"] > 6.0 for r in rows) / n,
            "flew_over_raised_ground": sum(over) / n}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("actors", nargs="+", metavar="LABEL=ACTOR",
                    help="an actor file, run directory or shipped:NAME, with a label")
    ap.add_argument("--families", nargs="+", default=list(FAMILIES), choices=FAMILIES)
    ap.add_argument("--worlds", type=int, default=20)
    ap.add_argument("--episodes", type=int, default=40, help="per family and actor")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=None, help="figure")
    args = ap.parse_args()
    pairs = []
    for item in args.actors:
        label, eq, actor = item.partition("=")
        if not eq or not label or not actor:
            ap.error(f"actor {item!r}: expected LABEL=ACTOR")
        pairs.append((label, actor))
    from sitl.world.scenario import load_scenario

    results: dict = {}
    for label, actor in pairs:
        for family in args.families:
            rows = fly(actor, family, args.worlds, args.episodes)
            level = load_scenario(family).area.flight_level
            s = summary(rows, level)
            results.setdefault(label, {})[family] = {**s, "rows": rows}
            print(f"{label:10s} {family:8s} success {s['success']:.0%} timeout "
                  f"{s['timeout']:.0%} highest altitude median {s['max_altitude_median']:.1f} m, "
                  f"above 6 m {s['above_6m']:.0%}, over raised ground "
                  f"{s['flew_over_raised_ground']:.0%}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"actors": dict(pairs), "worlds": args.worlds,
                                         "validation": True, "results": results}, indent=1))
    if args.out:
        plot(results, args.families, args.out)


def plot(results: dict, families: list[str], out: Path) -> None:
    """The highest altitude per episode, a panel per family, a histogram per actor."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(families), figsize=(4 * len(families), 3.4),
                             squeeze=False, sharey=True)
    bins = np.arange(2.0, 14.5, 0.5)
    for ax, family in zip(axes[0], families, strict=True):
        for label, by_family in results.items():
            s = by_family[family]
            ax.hist([r["max_altitude"] for r in s["rows"]], bins=bins, alpha=0.5,
                    label=f"{label} ({s['success']:.0%} success)")
        ax.axvline(6.0, color="k", lw=0.8, ls="--")
        ax.set(title=family, xlabel="highest altitude in the episode (m)")
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("episodes")
    fig.suptitle("How high each policy flies (validation worlds; dashed: the goal's 6 m "
                 "ceiling)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
