"""``skyloop experiment run GRID.toml --out DIR``: a grid of ``skyloop train`` runs on Ray Tune.

Each trial is exactly a ``policy.training.train.Trainer`` run in ``DIR/<trial>/`` (CSV, checkpoints,
TensorBoard, curve, ``result.json``), started by Ray Tune as a function trainable. The
trial directory is the one source of truth for progress:

- a trial whose ``result.json`` covers its episodes is finished and is not scheduled;
- a trial with a checkpoint resumes from it (``Trainer.run(resume=True)``), so killing
  ``experiment run`` and rerunning the same command continues the grid, losing at most
  one checkpoint interval per running trial; a trial killed before its first
  checkpoint starts again from nothing.

One machine: Ray starts embedded with the machine's cores (nothing to set up), and at most
``cores // cpus_per_trial`` trials run at once (``--max-concurrent`` lowers it). A cluster:
``--address HOST:PORT`` or ``RAY_ADDRESS``; ``DIR`` must then be a path every node sees
(NFS or similar), since each trial writes its directory on the node that runs it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from policy.training.plots import CSV_NAME
from policy.training.train import CHECKPOINT, TrainConfig, Trainer, finished
from skyloop.experiment.grid import Grid

__all__ = ["run_grid", "grid_status"]

PARTIAL = (CSV_NAME, "config.json", "tb", "curve.png")  # a run without a checkpoint


def _train_trial(params: dict[str, Any], *, configs: dict[str, dict], out: str) -> None:
    """Ray Tune function trainable: one ``skyloop train`` run, resumed if it has begun."""
    from ray import tune

    name = params["trial"]
    config = TrainConfig(**configs[name])
    run_dir = Path(out) / name
    resume = (run_dir / CHECKPOINT).is_file()
    if not resume:  # killed before its first checkpoint: nothing to keep
        for part in PARTIAL:
            path = run_dir / part
            shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)

    def report(row: dict) -> None:
        tune.report({k: row[k] for k in ("episode", "success_rate_500", "collision_rate_500",
                                         "total_steps", "env_steps_per_s", "wall_s")})

    Trainer(config, run_dir).run(resume=resume, on_episode=report)


def grid_status(grid: Grid, out: Path) -> dict[str, str]:
    """Each trial's state from its directory: finished, started (has a checkpoint), or new."""
    status = {}
    for t in grid.trials:
        run_dir = out / t.name
        status[t.name] = ("finished" if finished(run_dir, t.config.episodes) else
                          "started" if (run_dir / CHECKPOINT).is_file() else "new")
    return status


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


class _Progress:
    """A Tune callback printing one line at most every ``every`` s: trials, episodes, the
    rates of episodes and env steps since this command started, and the ETA at that
    episode rate (episodes of a grid can differ in length: BipedalWalker's run from ~40 to
    2,000 steps, so the env-step rate is the steadier one)."""

    def __init__(self, grid: Grid, done_episodes: dict[str, int], every: float = 60.0) -> None:
        from ray.tune import Callback

        progress = self

        class _Callback(Callback):
            def on_trial_result(self, iteration, trials, trial, result, **info):
                name, episode = trial.config["trial"], int(result["episode"])
                # a trial restarted from an earlier checkpoint goes back: count gains only
                progress.gained += max(0, episode - progress.episodes.get(name, 0))
                progress.episodes[name] = episode
                steps = int(result["total_steps"])  # a trial's first report sets its base
                progress.gained_steps += max(0, steps - progress.steps.get(name, steps))
                progress.steps[name] = steps
                progress.maybe_print()

            def on_trial_complete(self, iteration, trials, trial, **info):
                progress.finished += 1
                progress.maybe_print(force=True, note=f"finished {trial.config['trial']}")

            def on_trial_error(self, iteration, trials, trial, **info):
                progress.maybe_print(force=True, note=f"FAILED {trial.config['trial']}")

        self.callback = _Callback()
        self.total = grid.episodes
        self.trials = len(grid.trials)
        self.episodes = dict(done_episodes)
        self.gained = 0  # episodes trained since this command started
        self.steps: dict[str, int] = {}  # env steps of each trial at its last report
        self.gained_steps = 0
        self.finished = sum(1 for t in grid.trials
                            if done_episodes.get(t.name, 0) >= t.config.episodes)
        self.t0 = self.last = time.monotonic()
        self.every = every

    def maybe_print(self, force: bool = False, note: str = "") -> None:
        now = time.monotonic()
        if not force and now - self.last < self.every:
            return
        self.last = now
        done = sum(self.episodes.values())
        rate = self.gained / max(now - self.t0, 1e-9) * 60.0
        step_rate = self.gained_steps / max(now - self.t0, 1e-9)
        eta = (self.total - done) / rate * 60.0 if rate > 0 else float("inf")
        eta_s = "?" if eta == float("inf") else f"{eta / 3600:.1f} h"
        print(f"[experiment] {self.finished}/{self.trials} trials finished, episodes "
              f"{done:,}/{self.total:,} ({done / self.total:.0%}), {rate:.1f} episodes/min, "
              f"{step_rate:,.0f} env steps/s, ETA {eta_s}" + (f"  ({note})" if note else ""),
              flush=True)


def _episodes_done(out: Path, grid: Grid, status: dict[str, str]) -> dict[str, int]:
    """Episodes in each trial's CSV (a progress estimate only); 0 for a trial that starts
    over (no checkpoint: its old CSV is dropped)."""
    done = {}
    for t in grid.trials:
        if status[t.name] == "new":
            done[t.name] = 0
            continue
        csv_path = out / t.name / CSV_NAME
        try:
            done[t.name] = max(0, sum(1 for _ in csv_path.open()) - 1)
        except OSError:
            done[t.name] = 0
    return done


def _honour_nice() -> None:
    """Give this session's autogroup this process's niceness (Linux).

    With autogroup scheduling (``/proc/sys/kernel/sched_autogroup_enabled``) the CPU is
    shared between sessions first and by niceness only inside one, so a grid started as
    ``setsid nice -n 19 skyloop experiment run ...`` still took half of a 2-core machine
    from interactive work (seen here). Only a session leader does this: from an
    interactive shell the group is the user's whole session."""
    try:
        niceness = os.nice(0)
        if niceness > 0 and os.getsid(0) == os.getpid():
            Path("/proc/self/autogroup").write_text(str(niceness))
    except OSError:
        pass


def run_grid(grid: Grid, out: Path, max_concurrent: int | None = None,
             address: str | None = None, cpus_per_trial: int | None = None
             ) -> dict[str, str]:
    """Run (or continue) every unfinished trial of ``grid`` under ``out``; returns the
    status of each trial afterwards."""
    _honour_nice()
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy(grid.path, out / "grid.toml")
    status = grid_status(grid, out)
    todo = [t for t in grid.trials if status[t.name] != "finished"]
    runs_path = out / "runs.json"
    runs = json.loads(runs_path.read_text()) if runs_path.exists() else []
    runs.append({"commit": _commit(), "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                 "python": sys.version.split()[0], "trials_to_run": [t.name for t in todo]})
    runs_path.write_text(json.dumps(runs, indent=2))
    print(f"[experiment] {grid.name}: {len(grid.trials)} trials, "
          f"{len(grid.trials) - len(todo)} finished, {len(todo)} to run -> {out}", flush=True)
    if not todo:
        return status

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")
    # the driver runs at nice 19 beside its own trials, where a Tune bookkeeping step can
    # take seconds: warn only past 30 s, not a log line a minute at the default 0.5 s
    os.environ.setdefault("TUNE_WARN_THRESHOLD_S", "30")
    import ray
    from ray import tune

    address = address or os.environ.get("RAY_ADDRESS")
    if address:
        ray.init(address=address, include_dashboard=False, log_to_driver=False)
    else:
        ray.init(address="local", num_cpus=os.cpu_count(), include_dashboard=False,
                 log_to_driver=False)
    if cpus_per_trial is None:  # a parallel trial runs a learner and a collector
        cpus_per_trial = 1 if all(t.config.sync for t in todo) else 2
    try:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        concurrent = max(1, cpus // cpus_per_trial)
        if max_concurrent:
            concurrent = min(concurrent, max_concurrent)
        configs = {t.name: asdict(t.config) for t in todo}
        trainable = tune.with_resources(
            tune.with_parameters(_train_trial, configs=configs, out=str(out)),
            {"cpu": cpus_per_trial})
        progress = _Progress(grid, _episodes_done(out, grid, status))
        tuner = tune.Tuner(
            trainable,
            param_space={"trial": tune.grid_search([t.name for t in todo])},
            tune_config=tune.TuneConfig(max_concurrent_trials=concurrent),
            run_config=tune.RunConfig(
                name=f"{grid.name}-{time.strftime('%Y%m%d-%H%M%S')}",
                storage_path=str(out / ".tune"), verbose=0,
                failure_config=tune.FailureConfig(max_failures=2),
                callbacks=[progress.callback]),
        )
        tuner.fit()
    finally:
        ray.shutdown()
    status = grid_status(grid, out)
    left = [name for name, s in status.items() if s != "finished"]
    print(f"[experiment] {grid.name}: {len(status) - len(left)}/{len(status)} trials finished"
          + (f"; unfinished: {', '.join(left)}" if left else ""), flush=True)
    return status
