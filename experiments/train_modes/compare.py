"""Sample efficiency of the training loops: ``sync`` against the parallel mode, with one
learner thread (``parallel``) and with two (``pipeline``, the default since 8ba4645;
``pipeline_bf16`` with bfloat16 matmuls).

Reads the grids of this folder (one directory per ``MODES`` entry, each run with
``skyloop experiment run experiments/train_modes/<mode>.toml --out .../<mode>``) and
writes ``COMPARE.md`` and ``compare.png``: success and collision over the last 500
episodes against episodes, per mode the mean over seeds with a min-max band, and a table
of the success window at a few episodes with the 95% t-interval across seeds.

Run: ``python experiments/train_modes/compare.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from skyloop.experiment.report import read_episodes, t_interval  # noqa: E402

HERE = Path(__file__).parent
MODES = ("sync", "parallel", "pipeline", "pipeline_bf16")
LABELS = {"sync": "sync", "parallel": "parallel, 1 learner thread",
          "pipeline": "parallel, 2 learner threads (default)",
          "pipeline_bf16": "the same, --precision bf16"}
AT = (100, 200, 300, 400)


def curves(mode: str, key: str) -> dict[str, np.ndarray]:
    runs = sorted((HERE / mode).glob("*/episodes.csv"))
    return {p.parent.name: read_episodes(p)[key] for p in runs}


def main() -> None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharex=True)
    modes = [m for m in MODES if (HERE / m / "runs.json").exists()]  # the grids run so far
    commits = sorted({r["commit"][:10] for m in modes
                      for r in json.loads((HERE / m / "runs.json").read_text())})
    lines = ["# Training loops: sync vs parallel (TD3+ABR, valley)", "",
             f"Grids {', '.join(f'`{m}.toml`' for m in modes)} (3 seeds, 400 episodes each), "
             f"run at commits {', '.join(commits)} (each grid's `runs.json`); written by "
             f"`python {Path(__file__).name}`.", "",
             "Success over the last 500 episodes (the trainer's `success_rate_500`), "
             "mean over seeds [95% t-interval] and each seed.", "",
             "| episode | " + " | ".join(LABELS[m] for m in modes) + " |",
             "|---|" + "---|" * len(modes)]
    table: dict[int, list[str]] = {a: [] for a in AT}
    colours = dict(zip(MODES, ("tab:blue", "tab:orange", "tab:green", "tab:red",
                               "tab:purple"), strict=True))
    for mode in modes:
        colour = colours[mode]
        for ax, key in zip(axes, ("success_rate_500", "collision_rate_500"), strict=True):
            runs = curves(mode, key)
            n = min(len(c) for c in runs.values())
            y = 100 * np.stack([c[:n] for c in runs.values()])
            x = np.arange(1, n + 1)
            ax.plot(x, y.mean(0), color=colour, label=f"{LABELS[mode]} ({len(runs)} seeds)")
            ax.fill_between(x, y.min(0), y.max(0), color=colour, alpha=0.2)
        for a in AT:
            values = [c[a - 1] for c in curves(mode, "success_rate_500").values()
                      if len(c) >= a]
            mean, lo, hi = t_interval(values)
            ci = f" [{100 * lo:.1f}, {100 * hi:.1f}]" if lo is not None else ""
            seeds = ", ".join(f"{100 * v:.1f}" for v in values)
            table[a].append(f"{100 * mean:.1f}%{ci} ({seeds})")
    lines += [f"| {a} | " + " | ".join(table[a]) + " |" for a in AT]
    for ax, name in zip(axes, ("success", "collision"), strict=True):
        ax.set_xlabel("episode")
        ax.set_ylabel(f"{name} rate over the last 500 episodes (%)")
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper left")
    fig.suptitle("TD3+ABR on the valley: mean over seeds, min-max band")
    fig.tight_layout()
    fig.savefig(HERE / "compare.png", dpi=110)
    lines += ["", "![sync vs parallel](compare.png)", ""]
    (HERE / "COMPARE.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
