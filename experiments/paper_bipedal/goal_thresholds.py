"""Which episodes would ABR have counted as reaching the goal, at other thresholds? (issue 10)

The grid ran ABR with ``goal_return = 0`` (grid.toml says why), and no TD3 episode of
any seed reached it, so ABR never rewrote a reward and TD3+ABR ran identical to TD3. The
paper does not say its threshold. This reads each TD3 trial's training CSV (the env's
own return per episode, ``base_return``) and prints, per seed and threshold, the share
of the 1,000 training episodes that reach it, the first episode that does, and how those
episodes ended: a 2,000-step timeout is a walker that stood (or shuffled) without
falling; below the threshold a fall costs -100. Since in ``--sync`` mode a TD3+ABR trial
with the same seed is TD3 until its first goal episode, this says when and on what kind
of episode ABR would have started acting at each threshold; nothing is trained.

    python experiments/paper_bipedal/goal_thresholds.py experiments/paper_bipedal \
        [--thresholds 0 -20 -40 -60 -80] [--json OUT]
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

MAX_STEPS = 2000  # BipedalWalkerHardcore-v3's time limit


def read_trial(run: Path) -> list[dict]:
    """(env return, steps) of every training episode of a trial, in order."""
    path = run / "episodes.csv"
    with path.open() as f:
        reader = csv.DictReader(f)
        missing = {"base_return", "steps"} - set(reader.fieldnames or [])
        if missing:
            raise SystemExit(f"{path}: no column {', '.join(sorted(missing))}")
        return [{"return": float(r["base_return"]), "steps": int(r["steps"])}
                for r in reader]


def at_threshold(episodes: list[dict], threshold: float) -> dict:
    """The episodes an ABR run would count as goal episodes (return >= threshold)."""
    goal = [i for i, e in enumerate(episodes) if e["return"] >= threshold]
    stood = sum(episodes[i]["steps"] >= MAX_STEPS for i in goal)
    return {"threshold": threshold, "goal_episodes": len(goal),
            "share": len(goal) / len(episodes) if episodes else 0.0,
            "first": goal[0] + 1 if goal else None,
            "of_them_timeouts": stood}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("grid", type=Path, help="the grid's output directory")
    p.add_argument("--thresholds", type=float, nargs="+", default=[0, -20, -40, -60, -80])
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args()
    runs = sorted(d for d in args.grid.glob("*-td3+ngr-s*") if (d / "episodes.csv").is_file())
    if not runs:
        raise SystemExit(f"{args.grid}: no TD3 (td3+ngr) trial with an episodes.csv")
    rows = []
    print("| seed | episodes | best return | " + " | ".join(
        f"return >= {t:g}" for t in args.thresholds) + " |")
    print("|---" * (3 + len(args.thresholds)) + "|")
    for run in runs:
        episodes = read_trial(run)
        if not episodes:
            print(f"{run.name}: no episode yet, left out")
            continue
        seed = run.name.rpartition("-s")[2]
        cells = [at_threshold(episodes, t) for t in args.thresholds]
        rows.append({"trial": run.name, "episodes": len(episodes),
                     "best_return": max(e["return"] for e in episodes), "thresholds": cells})
        print(f"| {seed} | {len(episodes)} | {rows[-1]['best_return']:.1f} | " + " | ".join(
            f"{c['share']:.1%} (first ep {c['first']}, {c['of_them_timeouts']} timeouts)"
            if c["goal_episodes"] else "none" for c in cells) + " |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
