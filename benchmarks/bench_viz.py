"""Viewer benchmark: how much the live 3D view (``skyloop up --viz``) slows lockstep.

Keys:

- ``viz_lockstep_steps_per_s``: control steps per second of ``skyloop up --lockstep``
  with ``--viz save:PATH.rrd`` (the viz node subscribes to the vehicle's topics and
  logs every step to Rerun, a scan every 5 steps; the save sink stands for the viewer
  so that the number is the node's cost, not a viewer's rendering on this machine's CPU).
- ``viz_lockstep_slowdown``: 1 - with / without, the medians of runs alternated in the
  same benchmark (goal: at most 0.10).

``peers`` holds ``stack_lockstep_steps_per_s``: the same runs without ``--viz``.
Full mode: 3 pairs of 5-episode runs; quick: 1 pair of 1 episode.
"""

from __future__ import annotations

import json
import statistics
import sys
import tempfile
from pathlib import Path

from benchmarks.bench_stack import run_up


def run(quick: bool) -> dict:
    pairs, episodes = (1, "1") if quick else (3, "5")
    plain, viz = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(pairs):
            plain.append(run_up("--lockstep", "--episodes", episodes)["steps_per_s"])
            rrd = Path(tmp) / f"view{k}.rrd"
            viz.append(run_up("--lockstep", "--episodes", episodes, "--viz",
                              f"save:{rrd}")["steps_per_s"])
    with_viz, without = statistics.median(viz), statistics.median(plain)
    return {
        "viz_lockstep_steps_per_s": with_viz,
        "viz_lockstep_slowdown": 1.0 - with_viz / without,
        "viz_runs_steps_per_s": viz,
        "peers": {"stack_lockstep_steps_per_s": without, "stack_runs_steps_per_s": plain},
    }


if __name__ == "__main__":
    print(json.dumps(run("--quick" in sys.argv), indent=2))
