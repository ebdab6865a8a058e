"""Training curves like the paper's Figure 4.2: success and collision rate over the last
500 episodes against episodes, and the episode return, several runs in one figure
(``skyloop plot DIR...``), titled with the runs' algorithm, reward, task and seed(s)
(from each run's ``config.json``)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

CSV_NAME = "episodes.csv"
CONFIG_NAME = "config.json"  # the run's TrainConfig, written by policy.training.train
RETURN_WINDOW = 100  # episodes in the return panel's moving mean


def read_curve(run_dir: Path) -> dict[str, list[float]]:
    """Columns ``episode``, ``success_rate_500``, ``collision_rate_500`` and ``return`` of
    a run's CSV."""
    path = Path(run_dir) / CSV_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no training CSV (is {run_dir} a training run?)")
    cols: dict[str, list[float]] = {"episode": [], "success_rate_500": [],
                                    "collision_rate_500": [], "return": []}
    with path.open(newline="") as f:
        for row in csv.DictReader(f):
            for key in cols:
                cols[key].append(float(row[key]))
    return cols


def run_title(run_dirs: list[Path]) -> str:
    """``TD3 + ABR on valley, seed 3`` for one run; each field's distinct values joined for
    several (``seeds 0, 1, 2``); empty when no run has a ``config.json``."""
    configs = []
    for run in run_dirs:
        try:
            configs.append(json.loads((Path(run) / CONFIG_NAME).read_text()))
        except (OSError, ValueError):
            continue
    if not configs:
        return ""

    def distinct(get) -> list[str]:
        return list(dict.fromkeys(str(get(c)) for c in configs))

    algos = distinct(lambda c: c.get("algo", "?").upper())
    rewards = distinct(lambda c: c.get("reward", "?").upper())
    tasks = distinct(lambda c: c.get("env") or c.get("scenario", "?"))
    seeds = distinct(lambda c: c.get("seed", "?"))
    return (f"{'/'.join(algos)} + {'/'.join(rewards)} on {', '.join(tasks)}, "
            f"seed{'s' if len(seeds) > 1 else ''} {', '.join(seeds)}")


def _moving_mean(values: list[float], window: int) -> np.ndarray:
    """Mean of the last ``window`` values at each point (fewer at the start)."""
    v = np.asarray(values, dtype=float)
    cums = np.concatenate([[0.0], np.cumsum(v)])
    idx = np.arange(1, len(v) + 1)
    lo = np.maximum(idx - window, 0)
    return (cums[idx] - cums[lo]) / (idx - lo)


def curve_figure(run_dirs: list[Path], labels: list[str] | None = None) -> plt.Figure:
    """Three panels (success, collision, return), one colour per run, integer episode
    ticks, the runs' title (``run_title``)."""
    fig, (ax_s, ax_c, ax_r) = plt.subplots(1, 3, figsize=(15, 4.3), sharex=True)
    for i, run in enumerate(run_dirs):
        curve = read_curve(run)
        label = labels[i] if labels else Path(run).name
        color = f"C{i % 10}"
        ep = curve["episode"]
        ax_s.plot(ep, [100 * v for v in curve["success_rate_500"]], color=color, label=label)
        ax_c.plot(ep, [100 * v for v in curve["collision_rate_500"]], color=color,
                  label=label)
        ax_r.plot(ep, curve["return"], color=color, alpha=0.25, linewidth=0.7)
        ax_r.plot(ep, _moving_mean(curve["return"], RETURN_WINDOW), color=color, label=label)
    for ax, name in ((ax_s, "success"), (ax_c, "collision")):
        ax.set_ylabel(f"{name} rate over the last 500 episodes (%)")
        ax.set_ylim(0, 100)
    ax_r.set_ylabel(f"episode return (faint; line: mean of the last {RETURN_WINDOW})")
    for ax in (ax_s, ax_c, ax_r):
        ax.set_xlabel("episode")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
    ax_s.legend(loc="upper left", fontsize=8)
    title = run_title(run_dirs)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def plot_runs(run_dirs: list[Path], out: Path, labels: list[str] | None = None) -> Path:
    """One PNG of ``curve_figure``."""
    fig = curve_figure(run_dirs, labels)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
