"""Training curves like the paper's Figure 4.2: success and collision rate over the last
500 episodes against episodes, several runs in one figure (``skyloop plot DIR...``)."""

from __future__ import annotations

import csv
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

CSV_NAME = "episodes.csv"


def read_curve(run_dir: Path) -> dict[str, list[float]]:
    """Columns ``episode``, ``success_rate_500``, ``collision_rate_500`` of a run's CSV."""
    path = Path(run_dir) / CSV_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no training CSV (is {run_dir} a training run?)")
    cols: dict[str, list[float]] = {"episode": [], "success_rate_500": [],
                                    "collision_rate_500": []}
    with path.open(newline="") as f:
        for row in csv.DictReader(f):
            for key in cols:
                cols[key].append(float(row[key]))
    return cols


def plot_runs(run_dirs: list[Path], out: Path, labels: list[str] | None = None) -> Path:
    """One PNG with two panels (success, collision), one line per run."""
    fig, (ax_s, ax_c) = plt.subplots(1, 2, figsize=(11, 4), sharex=True)
    for i, run in enumerate(run_dirs):
        curve = read_curve(run)
        label = labels[i] if labels else Path(run).name
        ax_s.plot(curve["episode"], [100 * v for v in curve["success_rate_500"]], label=label)
        ax_c.plot(curve["episode"], [100 * v for v in curve["collision_rate_500"]], label=label)
    for ax, name in ((ax_s, "success"), (ax_c, "collision")):
        ax.set_xlabel("episode")
        ax.set_ylabel(f"{name} rate over the last 500 episodes (%)")
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    ax_s.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
