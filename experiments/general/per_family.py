"""Training success per world family of mixture runs (issue 14).

A mixture run's ``episodes.csv`` does not name the world each episode flew, but the
world is the first thing an episode's reset draws from its seed (``sitl.episode``,
``sitl.world.families.WorldSource.draw``; episode ``i`` of a run with seed ``s`` has seed
``policy.training.train.episode_seed(s, i)``), so it is recovered exactly here.

    python experiments/general/per_family.py RUN_DIR [RUN_DIR ...] --out FIG.png

Prints success / timeout / collision per family in windows of 500 episodes and draws
success per family over episodes (a 250-episode moving window), three runs a row.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from policy.training.train import episode_seed  # noqa: E402
from sitl.world.families import WorldSource  # noqa: E402

WINDOW = 250
COLUMNS = 3  # panels a row


def families_of(run: Path) -> tuple[list[str], list[str]]:
    """(family, outcome) of each episode of a finished or running mixture run."""
    config = json.loads((run / "config.json").read_text())
    source = WorldSource.parse(config["scenario"])
    if source.fixed:
        raise ValueError(f"{run}: scenario {config['scenario']!r} is one world, not a mixture")
    with (run / "episodes.csv").open() as f:
        rows = list(csv.DictReader(f))
    fams = [source.draw(np.random.default_rng(episode_seed(config["seed"],
                                                           int(r["episode"]) - 1)))
            .partition("#")[0] for r in rows]
    return fams, [r["outcome"] for r in rows]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--out", type=Path, default=Path("per_family.png"))
    args = p.parse_args()
    cols = min(COLUMNS, len(args.runs))
    rows = -(-len(args.runs) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 4 * rows), squeeze=False)
    for ax in axes.flat[len(args.runs):]:
        ax.axis("off")
    for ax, run in zip(axes.flat, args.runs, strict=False):
        fams, outcomes = families_of(run)
        print(f"{run.name}:")
        for lo in range(0, len(fams), 500):
            cells = []
            for fam in sorted(set(fams)):
                window = zip(fams[lo:lo + 500], outcomes[lo:lo + 500], strict=True)
                got = [o for f, o in window if f == fam]
                if got:
                    cells.append(f"{fam} {got.count('success') / len(got):.0%} "
                                 f"(t {got.count('timeout') / len(got):.0%}, n={len(got)})")
            print(f"  episodes {lo + 1}-{min(lo + 500, len(fams))}: " + "; ".join(cells))
        for fam in sorted(set(fams)):
            idx = np.array([i for i, f in enumerate(fams) if f == fam])
            ok = np.array([outcomes[i] == "success" for i in idx], float)
            k = max(1, WINDOW // len(set(fams)))  # about WINDOW episodes of all families
            if len(ok) >= k:
                rate = np.convolve(ok, np.ones(k) / k, mode="valid")
                ax.plot(idx[k - 1:] + 1, rate, label=fam)
        ax.set(title=run.name, xlabel="training episode",
               ylabel=f"success (last ~{WINDOW} episodes, per family)", ylim=(0, 1))
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
