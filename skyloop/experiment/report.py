"""``skyloop experiment report DIR [--eval-episodes N]``: a grid's results, written into DIR.

Everything is read from the directory ``skyloop experiment run`` writes (``grid.toml``,
``runs.json``, one run directory per trial). A partial grid (trials unfinished or not
started, a CSV still being written) reports what it has and says how far each trial is.

``REPORT.md`` holds, after the grid file, its commits, the finished count, the command to
reproduce and the settings every trial shares, one section per task (scenario or env id):

- the methods table: success over the last 500 training episodes (mean over seeds with a
  95% t-interval across seeds, and each seed), the peak of the 500-episode success window,
  collision over the last 500, env steps, wall-clock, and the paper's figure beside ours;
  for a Gymnasium env the main number is the mean env return (``base_return``: without the
  goal reward's bonus) of the last 100 episodes;
- with ``--eval-episodes N``: each finished trial's final actor run deterministically (no
  exploration noise) on N held-out episodes seeded from ``policy.training.evaluate.EVAL_SEED``,
  with a Wilson interval per trial, cached in ``<trial>/eval_<N>.json`` under the actor
  file's SHA-256 (an unchanged actor is not evaluated again);
- the ordering of the methods computed from the data against the paper's: each adjacent
  pair of the paper's ordering, whether it holds here, the gap and whether the 95%
  intervals overlap;
- the paper's Figure 4.2 as ``curves_<task>.png`` (success and collision over the last 500
  against episodes; per method the mean over seeds with a min-max band); for an env, the
  100-episode moving mean of the env return and the success window;
- analysis facts from the CSVs: the eq. 3.5 terms' mean per episode over the last 500 and
  their share of the return, ABR's new versus reused patterns per 500-episode block, the
  goal bonus against the base return on goal episodes (quantiles; ``bonus_<task>.png``),
  and episode length by outcome.

``summary.json`` holds the same numbers per trial and per (task, method). The metrics are
small pure functions of a CSV's columns (``read_episodes``, ``trial_metrics``,
``t_interval``, ``ordering``); ``write_report`` gathers, evaluates and writes.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import re
import time
import tomllib
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from bus.task import episode_outcome
from policy.training.plots import CSV_NAME  # importing it selects matplotlib's Agg backend
from policy.training.rollout import EpisodeResult, summarize
from policy.training.train import ACTOR, RESULT, REWARD_TERMS, WINDOW, TrainConfig, finished
from skyloop.experiment.grid import PER_TRIAL, Grid, Trial, load_grid

__all__ = ["PAPER", "read_episodes", "trailing_mean", "trial_metrics", "t_interval",
           "aggregate", "ordering", "evaluate_trial", "write_report"]

RETURN_WINDOW = 100  # the paper's BipedalWalker number: mean return of the last 100
BLOCK = 500  # ABR pattern statistics per block of episodes
OUTCOMES = ("success", "collision", "timeout")
BONUS_REWARDS = ("abr", "egr", "tr")  # the variants that add a goal bonus
QUANTILES = (0.0, 0.1, 0.5, 0.9, 1.0)
TERMS = tuple(f"r_{k}" for k in REWARD_TERMS)
EVAL_HINT = 200  # --eval-episodes in the reproduce command

# The paper's numbers (abr-method.md, "Results to compare against"): success over the last
# 500 of 5000 episodes and the peak of that window; BipedalWalkerHardcore: mean return of
# the last 100 of 1000 episodes (TD3 there is our td3+ngr: the env's reward, no bonus).
PAPER: dict[str, dict[str, dict[str, float]]] = {
    "valley": {
        "ddpg+tr": {"success_last500": 0.378, "peak_success500": 0.46},
        "td3+tr": {"success_last500": 0.422, "peak_success500": 0.573},
        "td3+ngr": {"success_last500": 0.536},
        "td3+egr": {"success_last500": 0.692},
        "td3+abr": {"success_last500": 0.848},
    },
    "dynamic": {
        "ddpg+tr": {"success_last500": 0.006},
        "td3+tr": {"success_last500": 0.37, "peak_success500": 0.738},
        "td3+ngr": {"success_last500": 0.478},
        "td3+egr": {"success_last500": 0.55},
        "td3+abr": {"success_last500": 0.616, "peak_success500": 0.74},
    },
    "BipedalWalkerHardcore-v3": {
        "td3+ngr": {"return_last100": -89.61},
        "td3+abr": {"return_last100": -70.91},
    },
}

NAN = float("nan")
TEXT_COLUMNS = ("outcome", "world")  # the CSV's columns that are not numbers


# -- pure helpers: columns, windows, intervals ---------------------------------------------

def read_episodes(path: Path) -> dict[str, np.ndarray]:
    """A training CSV's columns: ``outcome`` as strings, every other column as floats.

    A missing or empty file gives ``{}``; a header alone gives empty columns. A last line
    without its newline (a run still writing) is dropped, and so is every row from the
    first one that does not parse. Missing columns (older CSVs) are simply absent.
    """
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError):
        return {}
    if text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    reader = csv.DictReader(io.StringIO(text))
    names = list(reader.fieldnames or [])
    rows: list[dict[str, Any]] = []
    for row in reader:
        if None in row or any(v is None for v in row.values()):
            break  # too many or too few fields
        try:
            rows.append({k: (v if k in TEXT_COLUMNS else float(v)) for k, v in row.items()})
        except ValueError:
            break
    return {k: np.array([r[k] for r in rows], dtype=str if k in TEXT_COLUMNS else float)
            for k in names}


def n_episodes(cols: dict[str, np.ndarray]) -> int:
    return len(next(iter(cols.values()))) if cols else 0


def trailing_mean(x: Sequence[float] | np.ndarray, window: int) -> np.ndarray:
    """At each episode i, the mean of the last ``min(i + 1, window)`` values: with
    ``x = outcome == "success"`` and ``window = 500`` it is the trainer's
    ``success_rate_500``."""
    x = np.asarray(x, float)
    c = np.concatenate([[0.0], np.cumsum(x)])
    i = np.arange(1, len(x) + 1)
    lo = np.maximum(0, i - window)
    return (c[i] - c[lo]) / (i - lo)


def _mean(x: np.ndarray) -> float:
    return float(np.mean(x)) if len(x) else NAN


def _finite(v: Any) -> bool:
    return isinstance(v, int | float | np.number) and not isinstance(v, bool) \
        and math.isfinite(float(v))


def _quantiles(x: np.ndarray) -> dict[str, float] | None:
    if not len(x):
        return None
    return {f"q{round(100 * q)}": float(np.quantile(x, q)) for q in QUANTILES}


def reward_terms(cols: dict[str, np.ndarray], window: int = WINDOW) -> dict | None:
    """Mean per episode over the last ``window`` episodes of each eq. 3.5 term and of the
    goal bonus (return - base_return); ``None`` when the CSV has no terms or they are all
    zero (a Gymnasium env)."""
    present = [t for t in TERMS if t in cols]
    if not n_episodes(cols) or not present or not any(np.any(cols[t][-window:] != 0)
                                                     for t in present):
        return None
    means = {t: _mean(cols[t][-window:]) for t in present}
    if "return" in cols and "base_return" in cols:
        means["goal_bonus"] = _mean((cols["return"] - cols["base_return"])[-window:])
    return means


def term_shares(means: dict[str, float]) -> dict[str, float]:
    """Each term's share of the return's magnitude: |mean| / sum of |means|."""
    total = sum(abs(v) for v in means.values() if _finite(v))
    return {k: abs(v) / total if total and _finite(v) else NAN for k, v in means.items()}


def abr_blocks(cols: dict[str, np.ndarray], block: int = BLOCK) -> list[dict] | None:
    """ABR's pattern statistics per ``block`` episodes: groups processed, groups that
    made a new pattern, and the size of the pattern set H at the block's end."""
    keys = ("abr_patterns", "abr_new_patterns", "abr_groups")
    n = n_episodes(cols)
    if not n or not all(k in cols for k in keys):
        return None
    out = []
    for start in range(0, n, block):
        end = min(start + block, n)
        groups = int(cols["abr_groups"][start:end].sum())
        new = int(cols["abr_new_patterns"][start:end].sum())
        out.append({"first": start + 1, "last": end, "groups": groups, "new_patterns": new,
                    "new_share": new / groups if groups else NAN,
                    "patterns_at_end": int(cols["abr_patterns"][end - 1])})
    return out


def trial_metrics(cols: dict[str, np.ndarray]) -> dict[str, Any]:
    """Every per-trial number of the report, from a CSV's columns (``read_episodes``)."""
    n = n_episodes(cols)
    m: dict[str, Any] = {"episodes": n, "window": min(n, WINDOW)}
    outcome = cols.get("outcome")
    for o in OUTCOMES:
        m[f"{o}_last500"] = _mean((outcome == o)[-WINDOW:]) if outcome is not None else NAN
    m["peak_success500"], m["peak_episode"] = NAN, None
    if outcome is not None and n >= WINDOW:
        curve = trailing_mean(outcome == "success", WINDOW)[WINDOW - 1:]
        k = int(np.argmax(curve))
        m["peak_success500"], m["peak_episode"] = float(curve[k]), k + WINDOW
    for key, col in (("return_last100", "base_return"), ("learning_return_last100", "return")):
        m[key] = _mean(cols[col][-RETURN_WINDOW:]) if col in cols else NAN
    m["best_return"], m["best_return_episode"] = NAN, None  # the base (env's own) return
    if n and "base_return" in cols:
        k = int(np.argmax(cols["base_return"]))
        m["best_return"], m["best_return_episode"] = float(cols["base_return"][k]), k + 1
    if n and "total_steps" in cols:
        m["env_steps"] = int(cols["total_steps"][-1])
    else:
        m["env_steps"] = int(cols["steps"].sum()) if n and "steps" in cols else None
    m["goal_episodes"] = int((outcome == "success").sum()) if outcome is not None else 0
    m["steps_by_outcome"] = None
    if outcome is not None and "steps" in cols:
        last, steps = outcome[-WINDOW:], cols["steps"][-WINDOW:]
        m["steps_by_outcome"] = {o: {"episodes": int((last == o).sum()),
                                     "mean_steps": _mean(steps[last == o])} for o in OUTCOMES}
    m["reward_terms"] = reward_terms(cols)
    m["abr_blocks"] = abr_blocks(cols)
    m["abr_final_patterns"] = (int(cols["abr_patterns"][-1])
                               if n and "abr_patterns" in cols else None)
    return m


def goal_bonus(cols: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(goal bonus, base return) of the goal episodes: bonus = return - base_return."""
    if not all(k in cols for k in ("outcome", "return", "base_return")):
        return np.zeros(0), np.zeros(0)
    goal = cols["outcome"] == "success"
    return (cols["return"] - cols["base_return"])[goal], cols["base_return"][goal]


IDENTITY_COLUMNS = ("return", "steps", "total_steps")


def identical_pairs(cols_by_method: dict[str, dict[int, dict[str, np.ndarray]]]
                    ) -> list[dict[str, Any]]:
    """Pairs of methods whose trials of one seed ran the same episodes: equal
    ``IDENTITY_COLUMNS`` in every row the two CSVs both have (at least one; ``episodes``,
    with ``of`` each trial's count when one is further on). In sync mode two goal rewards
    of one seed stay identical until the first goal episode where they differ (TD3+ABR and
    TD3+NGR before any goal), so a pair found here is a method that never acted in those
    episodes. ``cols_by_method``: method -> seed -> CSV columns."""
    pairs = []
    methods = list(cols_by_method)
    for i, a in enumerate(methods):
        for b in methods[i + 1:]:
            for seed in sorted(set(cols_by_method[a]) & set(cols_by_method[b])):
                ca, cb = cols_by_method[a][seed], cols_by_method[b][seed]
                na, nb = n_episodes(ca), n_episodes(cb)
                n = min(na, nb)
                if not n or not all(k in ca and k in cb and np.array_equal(ca[k][:n], cb[k][:n])
                                    for k in IDENTITY_COLUMNS):
                    continue
                pairs.append({"methods": [a, b], "seed": seed, "episodes": n, "of": [na, nb]})
    return pairs


def t_interval(values: Iterable[float], confidence: float = 0.95
               ) -> tuple[float, float | None, float | None]:
    """(mean, lo, hi): the t-interval of the mean across seeds; lo = hi = None with fewer
    than two values (undefined), the mean itself when every value is the same."""
    x = np.array([float(v) for v in values if _finite(v)])
    if not len(x):
        return NAN, None, None
    mean = float(x.mean())
    if len(x) < 2:
        return mean, None, None
    sem = float(stats.sem(x))
    if sem == 0.0:
        return mean, mean, mean
    lo, hi = stats.t.interval(confidence, len(x) - 1, loc=mean, scale=sem)
    return mean, float(lo), float(hi)


def aggregate(per_seed: dict[int, Any], rate: bool = False) -> dict[str, Any]:
    """Mean over seeds, its 95% t-interval and the per-seed values (finite ones only).
    For a ``rate`` the interval is clipped to [0, 1] (with two or three seeds the
    t-interval of a success rate easily reaches past 100%)."""
    seeds = [s for s, v in per_seed.items() if _finite(v)]
    values = [float(per_seed[s]) for s in seeds]
    mean, lo, hi = t_interval(values)
    if rate and lo is not None and hi is not None:
        lo, hi = max(lo, 0.0), min(hi, 1.0)
    return {"mean": mean, "lo": lo, "hi": hi, "n": len(values), "seeds": seeds,
            "values": values}


def _overlap(a: dict, b: dict) -> bool | None:
    if a["lo"] is None or b["lo"] is None:
        return None
    return a["lo"] <= b["hi"] and b["lo"] <= a["hi"]


def ordering(task: str, stats_by_method: dict[str, dict], metric: str,
             paper_metric: str | None = None) -> dict[str, Any]:
    """The methods sorted by ``metric`` (an ``aggregate`` per method; higher is better)
    against the paper's ordering of the same methods by ``paper_metric`` (default: the
    same metric), pair by adjacent pair of the paper's ordering."""
    present = [m for m, a in stats_by_method.items() if _finite(a["mean"])]
    ours = sorted(present, key=lambda m: -stats_by_method[m]["mean"])
    paper_task = PAPER.get(task, {})
    metric_p = paper_metric or metric
    paper = sorted((m for m in present if metric_p in paper_task.get(m, {})),
                   key=lambda m: -paper_task[m][metric_p])
    pairs = []
    for better, worse in zip(paper, paper[1:], strict=False):
        a, b = stats_by_method[better], stats_by_method[worse]
        gap = a["mean"] - b["mean"]
        pairs.append({"better": better, "worse": worse, "holds": bool(gap > 0), "gap": gap,
                      "intervals_overlap": _overlap(a, b)})
    return {"metric": metric, "ours": ours,
            "ours_values": {m: stats_by_method[m]["mean"] for m in ours},
            "paper": paper, "paper_values": {m: paper_task[m][metric_p] for m in paper},
            "pairs": pairs, "pairs_holding": sum(p["holds"] for p in pairs),
            "all_hold": bool(pairs) and all(p["holds"] for p in pairs)}


# -- trials ----------------------------------------------------------------------------------

@dataclass
class TrialData:
    trial: Trial
    run_dir: Path
    status: str  # "finished" | "unfinished" | "no episodes" | "not started"
    cols: dict[str, np.ndarray]
    metrics: dict[str, Any]
    wall_s: float | None
    config_diff: list[str] = field(default_factory=list)
    eval: dict | None = None

    @property
    def config(self) -> TrainConfig:
        return self.trial.config

    @property
    def task(self) -> str:
        return self.config.task

    @property
    def is_gym(self) -> bool:
        return bool(self.config.env)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _config_diff(trial: Trial, run_dir: Path) -> list[str]:
    """Options where the trial's ``config.json`` differs from what the grid asks for."""
    saved = _read_json(run_dir / "config.json")
    if not isinstance(saved, dict):
        return []
    want = asdict(trial.config)
    return [f"{k}={saved.get(k)!r} (grid: {v!r})" for k, v in want.items()
            if k != "progress" and saved.get(k, v) != v]


def load_trial(trial: Trial, grid_dir: Path) -> TrialData:
    run_dir = grid_dir / trial.name
    csv_path = run_dir / CSV_NAME
    cols = read_episodes(csv_path)
    metrics = trial_metrics(cols)
    done = finished(run_dir, trial.config.episodes)
    status = ("finished" if done else "not started" if not csv_path.is_file() else
              "no episodes" if not metrics["episodes"] else "unfinished")
    result = _read_json(run_dir / RESULT) if done else None
    wall = result.get("wall_s") if isinstance(result, dict) else None
    return TrialData(trial, run_dir, status, cols, metrics,
                     float(wall) if _finite(wall) else None, _config_diff(trial, run_dir))


# -- evaluation -----------------------------------------------------------------------------

def _evaluate_scenario(actor: Path, config: TrainConfig, episodes: int) -> dict:
    """``policy.training.evaluate.evaluate`` in the trial's own env (its LiDAR range, frames
    and icosahedron radius: ``policy.training.train.make_envs``)."""
    import torch

    from policy.training.evaluate import EVAL_SEED, ActorController
    from policy.training.rollout import run_episodes
    from policy.training.train import make_envs

    torch.set_num_threads(1)
    controller = ActorController(actor, task=None)  # the trial's task, not the default's
    env = make_envs(asdict(config), 1)[0]
    t = controller.trained_task
    if ((t.frames, t.ico_radius) != (env.task.frames, env.task.ico_radius)
            or controller.trained_observation != env.obs_config):
        env.close()  # (a grid rerun into this directory with another state)
        raise ValueError(f"{actor}: trained for {t.frames} frames, radius {t.ico_radius:g} "
                         f"m, {controller.trained_observation.encoding} encoding; the grid "
                         f"asks for {env.task.frames}, {env.task.ico_radius:g} m, "
                         f"{env.obs_config.encoding}")
    try:
        results = list(run_episodes(env, controller, episodes, EVAL_SEED))
    finally:
        env.close()
    return {**summarize(results), "scenario": config.scenario}


def _evaluate_gym(actor: Path, config: TrainConfig, episodes: int) -> dict:
    """The actor on ``GymTask(config.env, config.goal_return)``; episode i reset with seed
    EVAL_SEED + i; success = the episode's return reached ``goal_return``."""
    import torch

    from policy.training.evaluate import EVAL_SEED, ActorController
    from policy.training.gym_task import GymTask

    torch.set_num_threads(1)
    controller = ActorController(actor, task=None)  # flattens the (frames, obs_dim) state
    task = GymTask(config.env, config.goal_return)
    results = []
    try:
        for i in range(episodes):
            state, _ = task.reset(seed=EVAL_SEED + i)
            total, steps = 0.0, 0
            while True:
                state, reward, terminated, truncated, info = task.step(controller(state))
                total += reward
                steps += 1
                if terminated or truncated:
                    break
            outcome = episode_outcome(info["goal_reached"], info["collision"])
            none = np.zeros((0, 3))
            results.append(EpisodeResult(EVAL_SEED + i, outcome, steps, total, 0.0,
                                         none, none, none))
    finally:
        task.close()
    summary = summarize(results)
    summary.pop("mean_path_length")
    return {**summary, "env": config.env, "goal_return": config.goal_return}


def evaluate_trial(run_dir: Path, config: TrainConfig, episodes: int) -> dict | None:
    """The trial's final actor on ``episodes`` held-out episodes, cached as
    ``eval_<episodes>.json`` under the actor's SHA-256; ``None`` without an actor."""
    from policy.training.evaluate import EVAL_SEED

    actor = run_dir / ACTOR
    if not actor.is_file():
        return None
    digest = hashlib.sha256(actor.read_bytes()).hexdigest()
    cache = run_dir / f"eval_{episodes}.json"
    cached = _read_json(cache)
    if (isinstance(cached, dict) and cached.get("actor_sha256") == digest
            and cached.get("episodes") == episodes and cached.get("seed") == EVAL_SEED):
        return cached
    print(f"[report] evaluating {run_dir.name} on {episodes} held-out episodes", flush=True)
    run = _evaluate_gym if config.env else _evaluate_scenario
    try:
        result = run(actor, config, episodes)
    except ValueError as exc:  # an unreadable actor: say so, cache nothing
        return {"error": str(exc), "episodes": episodes}
    result.update(seed=EVAL_SEED, deterministic=True, actor=str(actor), actor_sha256=digest,
                  actor_mtime=actor.stat().st_mtime)
    tmp = cache.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(result, indent=2))
    os.replace(tmp, cache)
    return result


def _eval_fields(ev: dict | None) -> dict[str, Any]:
    ok = isinstance(ev, dict) and "error" not in ev
    return {"eval_episodes": ev.get("episodes") if ok else None,
            "eval_success": ev.get("success_rate") if ok else None,
            "eval_success_ci95": ev.get("success_ci95") if ok else None,
            "eval_collision": ev.get("collision_rate") if ok else None,
            "eval_collision_ci95": ev.get("collision_ci95") if ok else None,
            "eval_return": ev.get("mean_return") if ok else None,
            "eval_error": ev.get("error") if isinstance(ev, dict) else None}


# -- gathering -----------------------------------------------------------------------------

TRIAL_METRICS = ("success_last500", "collision_last500", "peak_success500", "return_last100",
                 "learning_return_last100", "env_steps", "episodes")
EVAL_METRICS = ("eval_success", "eval_collision", "eval_return")
RATES = ("success_last500", "collision_last500", "peak_success500", "eval_success",
         "eval_collision")  # fractions in [0, 1]


def trial_record(td: TrialData) -> dict[str, Any]:
    m = td.metrics
    rec = {"trial": td.trial.name, "algo": td.config.algo, "reward": td.config.reward,
           "method": td.trial.method, "env": td.task,
           "kind": "env" if td.is_gym else "scenario", "seed": td.config.seed,
           "status": td.status, "episodes": m["episodes"],
           "episodes_planned": td.config.episodes, "finished": td.status == "finished",
           "wall_s": td.wall_s, "config_differs_from_grid": td.config_diff}
    rec.update({k: v for k, v in m.items() if k != "episodes"})
    rec.update(_eval_fields(td.eval), eval=td.eval)
    return rec


def method_entry(task: str, method: str, trials: list[TrialData]) -> dict[str, Any]:
    """One (task, method): every metric's mean over the seeds that have episodes, its
    95% t-interval and per-seed values, and the pooled analysis numbers."""
    started = [t for t in trials if t.metrics["episodes"]]
    recs = {t.config.seed: trial_record(t) for t in started}
    entry: dict[str, Any] = {
        "task": task, "method": method, "algo": trials[0].config.algo,
        "reward": trials[0].config.reward, "kind": "env" if trials[0].is_gym else "scenario",
        "n_seeds": len(started), "seeds_planned": [t.config.seed for t in trials],
        "seeds_finished": [t.config.seed for t in trials if t.status == "finished"],
        "episodes_planned": trials[0].config.episodes,
    }
    for key in (*TRIAL_METRICS, "wall_s", *EVAL_METRICS):
        entry[key] = aggregate({s: r[key] for s, r in recs.items()}, rate=key in RATES)
    terms = [t.metrics["reward_terms"] for t in started if t.metrics["reward_terms"]]
    if terms:
        means = {k: float(np.mean([d[k] for d in terms if k in d])) for k in terms[0]}
        entry["reward_terms"] = {k: {"mean": v, "share": s}
                                 for (k, v), s in zip(means.items(), term_shares(means).values(),
                                                      strict=True)}
    else:
        entry["reward_terms"] = None
    entry["abr"] = _method_abr(started) if trials[0].config.reward == "abr" else None
    bonus = [goal_bonus(t.cols) for t in started]
    b = np.concatenate([x for x, _ in bonus]) if bonus else np.zeros(0)
    base = np.concatenate([y for _, y in bonus]) if bonus else np.zeros(0)
    nonzero = np.abs(base) > 0
    entry["goal_bonus"] = {"goal_episodes": len(b), "bonus": _quantiles(b),
                           "base_return": _quantiles(base),
                           "bonus_over_abs_base": _quantiles(b[nonzero] / np.abs(base[nonzero]))}
    entry["steps_by_outcome"] = {}
    for o in OUTCOMES:
        per = [t.metrics["steps_by_outcome"][o] for t in started if t.metrics["steps_by_outcome"]]
        entry["steps_by_outcome"][o] = {
            "episodes": sum(p["episodes"] for p in per),
            "mean_steps": aggregate({i: p["mean_steps"] for i, p in enumerate(per)})["mean"]}
    return entry


def _method_abr(trials: list[TrialData]) -> dict[str, Any] | None:
    """ABR blocks summed over seeds: sum(new) / sum(groups) per 500-episode block."""
    per_seed = [t.metrics["abr_blocks"] for t in trials if t.metrics["abr_blocks"]]
    if not per_seed:
        return None
    blocks = []
    for i in range(max(len(b) for b in per_seed)):
        rows = [b[i] for b in per_seed if i < len(b)]
        groups, new = sum(r["groups"] for r in rows), sum(r["new_patterns"] for r in rows)
        blocks.append({"first": rows[0]["first"], "last": max(r["last"] for r in rows),
                       "seeds": len(rows), "groups": groups, "new_patterns": new,
                       "new_share": new / groups if groups else NAN,
                       "patterns_at_end_mean": float(np.mean([r["patterns_at_end"]
                                                              for r in rows]))})
    final = {t.config.seed: t.metrics["abr_final_patterns"] for t in trials}
    return {"blocks": blocks, "final_patterns": final}


# -- figures ---------------------------------------------------------------------------------

def _slug(task: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", task)


def _band(curves: list[np.ndarray]) -> tuple[np.ndarray, ...]:
    """Episode numbers and the mean, min and max across curves of unequal length (each
    episode over the seeds that have reached it)."""
    a = np.full((len(curves), max(len(c) for c in curves)), np.nan)
    for i, c in enumerate(curves):
        a[i, : len(c)] = c
    return np.arange(1, a.shape[1] + 1), np.nanmean(a, 0), np.nanmin(a, 0), np.nanmax(a, 0)


def _curve(cols: dict[str, np.ndarray], key: str) -> np.ndarray | None:
    if key == "return":
        return trailing_mean(cols["base_return"], RETURN_WINDOW) if "base_return" in cols \
            else None
    return trailing_mean(cols["outcome"] == key, WINDOW) if "outcome" in cols else None


def plot_curves(task: str, by_method: dict[str, list[TrialData]], is_gym: bool,
                out: Path) -> Path | None:
    """Figure 4.2: two panels, one line per method (mean over seeds, band min-max)."""
    import matplotlib.pyplot as plt

    panels = ([("return", f"env return, {RETURN_WINDOW}-episode moving mean", 1.0),
               ("success", f"success (return >= goal) over the last {WINDOW} (%)", 100.0)]
              if is_gym else
              [("success", f"success rate over the last {WINDOW} episodes (%)", 100.0),
               ("collision", f"collision rate over the last {WINDOW} episodes (%)", 100.0)])
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharex=True)
    drawn = False
    for method, trials in by_method.items():
        for ax, (key, _, scale) in zip(axes, panels, strict=True):
            curves = [c for t in trials if t.metrics["episodes"]
                      if (c := _curve(t.cols, key)) is not None]
            if not curves:
                continue
            x, mean, lo, hi = _band(curves)
            (line,) = ax.plot(x, scale * mean, lw=1.2, label=f"{method} (n={len(curves)})")
            ax.fill_between(x, scale * lo, scale * hi, color=line.get_color(), alpha=0.18,
                            linewidth=0)
            drawn = True
    if not drawn:
        plt.close(fig)
        return None
    for ax, (_, label, scale) in zip(axes, panels, strict=True):
        ax.set_xlabel("episode")
        ax.set_ylabel(label)
        if scale == 100.0:
            ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    fig.suptitle(f"{task}: mean over seeds, band = min-max across seeds", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def plot_bonus(task: str, by_method: dict[str, list[TrialData]], out: Path) -> Path | None:
    """Histograms of the goal bonus and of the base return on goal episodes (pooled over
    seeds) for the methods whose reward adds a bonus (ABR, EGR, TR)."""
    import matplotlib.pyplot as plt

    data = {}
    for method, trials in by_method.items():
        if trials[0].config.reward not in BONUS_REWARDS:
            continue
        pairs = [goal_bonus(t.cols) for t in trials]
        bonus = np.concatenate([b for b, _ in pairs])
        if len(bonus):
            data[method] = (bonus, np.concatenate([b for _, b in pairs]))
    if not data:
        return None
    fig, (ax_b, ax_r) = plt.subplots(1, 2, figsize=(11, 4))
    # shared bin edges: a constant bonus (TR's +50, up to float rounding) stays one bar
    edges = [np.histogram_bin_edges(np.concatenate([d[i] for d in data.values()]), bins=40)
             for i in (0, 1)]
    for method, (bonus, base) in data.items():
        label = f"{method} ({len(bonus)} goal episodes)"
        ax_b.hist(bonus, bins=edges[0], histtype="step", label=label)
        ax_r.hist(base, bins=edges[1], histtype="step", label=label)
    ax_b.set_xlabel("goal bonus of the episode (return - base_return)")
    ax_r.set_xlabel("base return of the episode (eq. 3.5 / env reward)")
    for ax in (ax_b, ax_r):
        ax.set_ylabel("goal episodes")
        ax.grid(alpha=0.3)
    ax_b.legend(loc="best", fontsize=8)
    fig.suptitle(f"{task}: goal episodes of all seeds", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


# -- formatting ------------------------------------------------------------------------------

def _pct(x: Any) -> str:
    return f"{100 * float(x):.1f}%" if _finite(x) else "—"


def _num(x: Any, digits: int = 2) -> str:
    return f"{float(x):,.{digits}f}" if _finite(x) else "—"


def _int(x: Any) -> str:
    return f"{int(round(float(x))):,}" if _finite(x) else "—"


def _dur(s: Any) -> str:
    if not _finite(s):
        return "—"
    s = float(s)
    return f"{s / 3600:.2f} h" if s >= 3600 else f"{s / 60:.1f} min" if s >= 60 else f"{s:.0f} s"


def _ci(a: dict, fmt=_pct) -> str:
    if not a["n"]:
        return "—"
    if a["lo"] is None:
        return f"{fmt(a['mean'])} (n=1)"
    return f"{fmt(a['mean'])} [{fmt(a['lo'])}, {fmt(a['hi'])}] (n={a['n']})"


def _gap(gap: float, metric: str) -> str:
    return (f"{100 * gap:+.1f} points" if metric.startswith(("success", "eval_success"))
            else f"{gap:+.2f}")


def _table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]


def _per_seed(trials: list[TrialData], key: str, fmt=_pct) -> str:
    parts = []
    for t in trials:
        v = trial_record(t).get(key)
        if not t.metrics["episodes"]:
            parts.append(f"s{t.config.seed} —")
            continue
        note = "" if t.status == "finished" else "*"
        if key.endswith("last500") and t.metrics["window"] < WINDOW:
            note += f" (last {t.metrics['window']})"
        if key == "peak_success500" and not _finite(v):
            note += " (< 500 ep)"
        parts.append(f"s{t.config.seed} {fmt(v)}{note}")
    return ", ".join(parts)


def _status(td: TrialData) -> str:
    n, planned = td.metrics["episodes"], td.config.episodes
    if td.status == "unfinished":
        return f"unfinished: {n:,}/{planned:,} episodes ({n / planned:.0%})"
    if td.status == "no episodes":
        return "no episodes (empty CSV)"
    return td.status


def _ordering_lines(o: dict, label: str, partial: bool) -> list[str]:
    fmt = _pct if o["metric"] in ("success_last500", "eval_success") else _num
    if not o["ours"]:
        return [f"**Ordering ({label})**: no method has data yet.", ""]
    lines = [f"**Ordering here ({label}, mean over seeds)**: "
             + " > ".join(f"{m} {fmt(o['ours_values'][m])}" for m in o["ours"])
             + (" (partial: some seeds unfinished)" if partial else "") + "."]
    if not o["paper"]:
        return lines + ["", "The paper gives no figure for these methods on this task.", ""]
    lines += ["", "**The paper's ordering** (of the methods in this grid): "
              + " > ".join(f"{m} {fmt(o['paper_values'][m])}" for m in o["paper"]) + ".", ""]
    if not o["pairs"]:
        return lines + ["Only one method of the paper's ordering has data here.", ""]
    rows = []
    for p in o["pairs"]:
        overlap = {None: "n/a (a method has one seed)", True: "overlap",
                   False: "do not overlap"}[p["intervals_overlap"]]
        holds = "holds" if p["holds"] else "tie: does not hold" if p["gap"] == 0 \
            else "does NOT hold"
        rows.append([f"{p['better']} > {p['worse']}", holds, _gap(p["gap"], o["metric"]),
                     overlap])
    lines += _table(["paper's pair", "here", "gap (first - second)", "95% intervals"], rows)
    lines += ["", f"{o['pairs_holding']} of {len(o['pairs'])} adjacent pairs of the paper's "
              f"ordering hold here; the paper's ordering "
              f"{'holds' if o['all_hold'] else 'does not hold'} as a whole.", ""]
    return lines


# -- the report ------------------------------------------------------------------------------

def _overview(grid: Grid, grid_dir: Path, runs: list, trials: list[TrialData]) -> list[str]:
    raw = tomllib.loads((grid_dir / "grid.toml").read_text())
    done = [t for t in trials if t.status == "finished"]
    tasks = list(dict.fromkeys(t.task for t in trials))
    methods = list(dict.fromkeys(t.trial.method for t in trials))
    seeds = list(dict.fromkeys(t.config.seed for t in trials))
    episodes = sorted({t.config.episodes for t in trials})
    lines = [f"# Experiment report: {grid.name}", "",
             f"Written {time.strftime('%Y-%m-%d %H:%M:%S %z')} by `skyloop experiment report` "
             f"from `{grid_dir}`.", "",
             f"- Grid file: `{grid_dir / 'grid.toml'}` (the copy `skyloop experiment run` "
             f"keeps): {len(trials)} trials = {len(tasks)} task(s) ({', '.join(tasks)}) x "
             f"{len(methods)} method(s) ({', '.join(methods)}) x {len(seeds)} seed(s) "
             f"({', '.join(map(str, seeds))})."]
    if runs:
        commits = list(dict.fromkeys(r.get("commit", "unknown") for r in runs))
        lines.append(f"- Commits ({len(commits)} distinct over {len(runs)} run(s) of the "
                     "grid; a resumed trial may span several):")
        for r in runs:
            lines.append(f"  - `{r.get('commit', 'unknown')}`: started {r.get('started', '?')},"
                         f" Python {r.get('python', '?')}, "
                         f"{len(r.get('trials_to_run', []))} trial(s) to run")
    else:
        lines.append("- Commits: unknown (no runs.json).")
    lines.append(f"- Trials finished: **{len(done)}/{len(trials)}**.")
    lines += ["- Reproduce:", "", "  ```",
              f"  skyloop experiment run {grid_dir / 'grid.toml'} --out {grid_dir}",
              f"  skyloop experiment report {grid_dir} --eval-episodes {EVAL_HINT}",
              "  ```", ""]
    train = raw.get("train", {})
    shared = [{k: v for k, v in asdict(t.config).items() if k not in PER_TRIAL | {"progress"}}
              for t in trials]
    same = all(s == shared[0] for s in shared)
    lines.append("- Budget and settings: that every method had the same budget and settings "
                 "is a property of the grid file, which gives every trial "
                 f"`episodes = {', '.join(map(str, episodes))}` and the same options. "
                 "Its `[train]` table: "
                 + (", ".join(f"`{k} = {v!r}`" for k, v in train.items()) or "(empty)")
                 + "; every other option at `TrainConfig`'s default. The options every trial "
                 f"runs with{' (the same for all trials)' if same else ' (THEY DIFFER)'}: "
                 + ", ".join(f"`{k}={v!r}`" for k, v in shared[0].items()) + ".")
    diffs = [t for t in trials if t.config_diff]
    lines.append("- Every started trial's `config.json` matches the grid." if not diffs else
                 "- `config.json` differs from the grid in: "
                 + "; ".join(f"{t.trial.name}: {', '.join(t.config_diff)}" for t in diffs))
    lines += ["", "## Trials", ""]
    lines += _table(["trial", "status", "episodes", "env steps", "wall-clock"],
                    [[t.trial.name, _status(t), f"{t.metrics['episodes']:,}/{t.config.episodes:,}",
                      _int(t.metrics["env_steps"]), _dur(t.wall_s)] for t in trials])
    unfinished = [t.trial.name for t in trials if t.status != "finished"]
    lines += ["", "Unfinished or not started: " + (", ".join(unfinished) or "none") + ".", ""]
    return lines


def _methods_table(task: str, by_method: dict[str, list[TrialData]], entries: dict[str, dict],
                   is_gym: bool) -> list[str]:
    paper = PAPER.get(task, {})
    rows = []
    for method, trials in by_method.items():
        e, p = entries[method], paper.get(method, {})
        seeds = f"{e['n_seeds']} ({len(e['seeds_finished'])} finished)"
        eps = ", ".join(f"{t.metrics['episodes']:,}" for t in trials)
        common = [_ci(e["collision_last500"]), _int(e["env_steps"]["mean"]),
                  _dur(e["wall_s"]["mean"])]
        if is_gym:
            rows.append([method, seeds, eps, _ci(e["return_last100"], _num),
                         _per_seed(trials, "return_last100", _num),
                         _num(p.get("return_last100")), _ci(e["success_last500"]),
                         *common])
        else:
            peak = (_ci(e["peak_success500"]) if e["peak_success500"]["n"] or not e["n_seeds"]
                    else "— (< 500 episodes)")
            rows.append([method, seeds, eps, _ci(e["success_last500"]),
                         _per_seed(trials, "success_last500"), _pct(p.get("success_last500")),
                         peak, _per_seed(trials, "peak_success500"),
                         _pct(p.get("peak_success500")), *common])
    tail = ["fall or collision (ended below the goal), last 500" if is_gym else
            "collision, last 500", "env steps (mean)", "wall-clock (mean, finished)"]
    if is_gym:
        header = ["method", "seeds", "episodes per seed",
                  f"env return, last {RETURN_WINDOW} [95% t]", "per seed", "paper",
                  "success (return >= goal), last 500", *tail]
    else:
        header = ["method", "seeds", "episodes per seed", "success, last 500 [95% t]",
                  "per seed", "paper", "peak 500-window success", "per seed", "paper peak",
                  *tail]
    lines = _table(header, rows)
    lines += ["", "Intervals: 95% t-interval of the mean across seeds (scipy.stats.t); "
              "n=1: undefined. `*`: the seed is unfinished; `(last k)`: fewer than 500 "
              "episodes so far. Peak: the highest success over a 500-episode window, once 500 "
              "episodes exist. The paper trained 5,000 episodes per method (1,000 for "
              "BipedalWalkerHardcore) in its own worlds: compare orderings and gaps, not "
              "absolute numbers.", ""]
    return lines


def _eval_table(by_method: dict[str, list[TrialData]], entries: dict[str, dict],
                is_gym: bool) -> list[str]:
    rows = []
    for method, trials in by_method.items():
        e = entries[method]
        seeds = []
        for t in trials:
            ev = t.eval
            if ev is None:
                seeds.append(f"s{t.config.seed} not evaluated ({_status(t)})")
            elif "error" in ev:
                seeds.append(f"s{t.config.seed} error: {ev['error']}")
            else:
                lo, hi = ev["success_ci95"]
                ret = f", return {_num(ev['mean_return'])}" if is_gym else ""
                seeds.append(f"s{t.config.seed} {_pct(ev['success_rate'])} "
                             f"[{_pct(lo)}, {_pct(hi)}]{ret}")
        main = (_ci(e["eval_return"], _num) if is_gym else _ci(e["eval_success"]))
        rows.append([method, main, _ci(e["eval_success"]) if is_gym else _ci(e["eval_collision"]),
                     "; ".join(seeds),
                     _ci(e["return_last100"], _num) if is_gym else _ci(e["success_last500"])])
    header = (["method", "eval mean return [95% t]", "eval success (return >= goal)",
               "per seed: success [Wilson 95%], return", "training: return, last 100"]
              if is_gym else
              ["method", "eval success [95% t]", "eval collision",
               "per seed: success [Wilson 95%]", "training: success, last 500"])
    return _table(header, rows) + [""]


def _cols_by_method(by_method: dict[str, list[TrialData]]
                    ) -> dict[str, dict[int, dict[str, np.ndarray]]]:
    return {m: {t.config.seed: t.cols for t in ts if n_episodes(t.cols)}
            for m, ts in by_method.items()}


def _analysis(by_method: dict[str, list[TrialData]], entries: dict[str, dict],
              same: list[dict[str, Any]]) -> list[str]:
    lines = ["### Analysis (computed from the CSVs)", ""]
    empty = [m for m, e in entries.items() if not e["n_seeds"]]
    if empty:
        lines += ["No episodes yet (left out below): " + ", ".join(empty) + ".", ""]
    if not len(empty) < len(entries):
        return lines
    term_rows = []
    for method, e in entries.items():
        terms = e["reward_terms"]
        if not terms:
            continue
        cells = [f"{_num(terms[k]['mean'], 1)} ({_pct(terms[k]['share'])})" if k in terms
                 else "—" for k in (*TERMS, "goal_bonus")]
        largest = max(terms, key=lambda k: terms[k]["share"]
                      if _finite(terms[k]["share"]) else -1)
        term_rows.append([method, *cells, largest])
    if term_rows:
        lines += ["**Which terms make up the learning return.** Per episode over the last 500 "
                  "episodes of each seed, mean over seeds; in brackets the share of the "
                  "return's magnitude, |mean| / sum of |means| of the six.", ""]
        lines += _table(["method", *TERMS, "goal bonus", "largest"], term_rows) + [""]
    else:
        lines += ["No eq. 3.5 terms in these CSVs (a Gymnasium env, or an older CSV).", ""]
    abr_rows, abr_final = [], []
    for method, e in entries.items():
        if not e["abr"]:
            continue
        for b in e["abr"]["blocks"]:
            abr_rows.append([method, f"{b['first']:,}-{b['last']:,}", b["seeds"],
                             f"{b['groups']:,}", f"{b['new_patterns']:,}",
                             _pct(b["new_share"]), _num(b["patterns_at_end_mean"], 1)])
        abr_final.append(f"{method}: " + ", ".join(
            f"s{s} {v if v is not None else '—'}" for s, v in e["abr"]["final_patterns"].items()))
    if abr_rows:
        lines += ["**ABR: new patterns against reused ones**, per 500-episode block, summed "
                  "over seeds: new / groups = the share of goal-episode groups that created "
                  "a pattern (the rest reused one).", ""]
        lines += _table(["method", "episodes", "seeds", "groups", "new patterns",
                         "new / groups", "size of H at block end (mean over seeds)"], abr_rows)
        lines += ["", "Final size of ABR's pattern set H per seed: " + "; ".join(abr_final)
                  + ".", ""]
    q = [f"q{round(100 * x)}" for x in QUANTILES]

    def qs(d: dict | None, digits: int = 1) -> str:
        return " / ".join(_num(d[k], digits) for k in q) if d else "—"

    if same:
        lines += ["**Identical trials**: these trials of one seed ran the same episodes, "
                  "return, steps and env steps equal in every CSV row both have: the goal "
                  "reward of one never changed a reward the other gave (in sync mode, no "
                  "goal episode at which they differ).", ""]
        lines += _table(["methods", "seed", "episodes"],
                        [[" = ".join(p["methods"]), str(p["seed"]),
                          f"{p['episodes']:,}" + ("" if p["of"][0] == p["of"][1] else
                                                 " (of {:,} / {:,})".format(*p["of"]))]
                         for p in same]) + [""]
    gym = [t for ts in by_method.values() for t in ts if t.is_gym and n_episodes(t.cols)]
    if gym:
        goal = gym[0].config.goal_return
        lines += [f"**Best env return of any episode** (the goal: {goal:g} or more), per "
                  "trial: " + "; ".join(
                      f"{t.trial.method} s{t.config.seed} {_num(t.metrics['best_return'])} "
                      f"(episode {t.metrics['best_return_episode']:,})" for t in gym) + ".", ""]
    bonus_rows = [[m, f"{e['goal_bonus']['goal_episodes']:,}", qs(e["goal_bonus"]["bonus"]),
                   qs(e["goal_bonus"]["base_return"]),
                   qs(e["goal_bonus"]["bonus_over_abs_base"], 3)]
                  for m, e in entries.items() if e["n_seeds"]]
    lines += ["**Goal bonus against base return on goal episodes** (every goal episode of "
              "every seed; quantiles " + " / ".join(q) + "; bonus = return - base_return).", ""]
    lines += _table(["method", "goal episodes", "goal bonus", "base return",
                     "bonus / abs(base return)"], bonus_rows) + [""]
    step_rows = []
    for m, e in entries.items():
        if not e["n_seeds"]:
            continue
        s = e["steps_by_outcome"]
        step_rows.append([m, *(f"{_num(s[o]['mean_steps'], 1)} ({s[o]['episodes']:,})"
                               for o in OUTCOMES)])
    lines += ["**Episode length by outcome** over the last 500 episodes: mean steps (mean "
              "over seeds of each seed's mean), in brackets the episodes summed over seeds.", ""]
    lines += _table(["method", *OUTCOMES], step_rows) + [""]
    return lines


def _clean(x: Any) -> Any:
    """JSON-safe: NaN and inf -> None, numpy scalars -> Python, tuples -> lists."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def write_report(grid_dir: Path, eval_episodes: int = 0) -> list[Path]:
    """Write ``REPORT.md``, ``summary.json`` and the figures into ``grid_dir``; with
    ``eval_episodes`` > 0 evaluate every finished trial's final actor first (cached).
    Returns the paths written."""
    grid_dir = Path(grid_dir)
    if not (grid_dir / "grid.toml").is_file():
        raise FileNotFoundError(f"{grid_dir}: no grid.toml (is it a directory written by "
                                "'skyloop experiment run'?)")
    if eval_episodes < 0:
        raise ValueError(f"--eval-episodes must be >= 0, got {eval_episodes}")
    grid = load_grid(grid_dir / "grid.toml")
    runs = _read_json(grid_dir / "runs.json")
    runs = runs if isinstance(runs, list) else []
    trials = [load_trial(t, grid_dir) for t in grid.trials]
    if eval_episodes:
        for td in trials:
            if td.status == "finished":
                td.eval = evaluate_trial(td.run_dir, td.config, eval_episodes)
    written: list[Path] = []
    lines = _overview(grid, grid_dir, runs, trials)
    if eval_episodes:
        lines += [f"Held-out evaluation: each finished trial's final actor, deterministic "
                  f"(no exploration noise), {eval_episodes} episodes with reset seeds "
                  f"1,000,000,000 + i (no training episode uses them); cached as "
                  f"`<trial>/eval_{eval_episodes}.json`. Unfinished trials are not evaluated "
                  f"(their actor is a checkpoint).", ""]
    methods_out, orderings, identical = [], {}, {}
    for task in dict.fromkeys(t.task for t in trials):
        by_method: dict[str, list[TrialData]] = {}
        for td in trials:
            if td.task == task:
                by_method.setdefault(td.trial.method, []).append(td)
        is_gym = next(iter(by_method.values()))[0].is_gym
        entries = {m: method_entry(task, m, ts) for m, ts in by_method.items()}
        methods_out += entries.values()
        metric = "return_last100" if is_gym else "success_last500"
        partial = any(t.status != "finished" for ts in by_method.values() for t in ts)
        orderings[task] = {"training": ordering(task, {m: e[metric] for m, e in
                                                       entries.items()}, metric)}
        first = next(iter(by_method.values()))[0].config
        kind = f"Gymnasium env, goal: return >= {first.goal_return:g}" if is_gym else "scenario"
        lines += [f"## {task} ({kind})", "", "### Methods (training)", ""]
        lines += _methods_table(task, by_method, entries, is_gym)
        label = (f"env return, last {RETURN_WINDOW}" if is_gym else "success, last 500")
        lines += ["### Ordering", ""]
        lines += _ordering_lines(orderings[task]["training"], label, partial)
        if eval_episodes:
            lines += [f"### Held-out evaluation ({eval_episodes} episodes per trial)", ""]
            lines += _eval_table(by_method, entries, is_gym)
            emetric = "eval_return" if is_gym else "eval_success"
            ev = ordering(task, {m: e[emetric] for m, e in entries.items()}, emetric,
                          paper_metric=metric)
            orderings[task]["eval"] = ev
            lines += _ordering_lines(ev, "held-out evaluation", partial)
        lines += ["### Figures", ""]
        curves = plot_curves(task, by_method, is_gym, grid_dir / f"curves_{_slug(task)}.png")
        if curves:
            written.append(curves)
            what = ("env return (100-episode moving mean) and success over the last 500"
                    if is_gym else "success and collision rate over the last 500 episodes "
                    "(the paper's Figure 4.2)")
            lines += [f"![curves]({curves.name})", "",
                      f"`{curves.name}`: {what} against episodes; per method the mean over "
                      "seeds (at each episode, over the seeds that reached it) with a min-max "
                      "band across seeds.", ""]
        else:
            lines += ["No episodes yet: no curves.", ""]
        bonus = plot_bonus(task, by_method, grid_dir / f"bonus_{_slug(task)}.png")
        if bonus:
            written.append(bonus)
            lines += [f"![goal bonus]({bonus.name})", "",
                      f"`{bonus.name}`: histograms of the goal bonus and of the base return "
                      "on goal episodes (all seeds) for the ABR, EGR and TR methods.", ""]
        else:
            lines += ["No goal episodes of an ABR, EGR or TR method yet: no bonus histogram.",
                      ""]
        identical[task] = identical_pairs(_cols_by_method(by_method))
        lines += _analysis(by_method, entries, identical[task])
    summary = {"grid": grid.name, "grid_file": str(grid_dir / "grid.toml"),
               "commits": list(dict.fromkeys(r.get("commit", "unknown") for r in runs)),
               "runs": runs, "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
               "trials_finished": sum(t.status == "finished" for t in trials),
               "trials_total": len(trials), "eval_episodes": eval_episodes or None,
               "trials": [trial_record(t) for t in trials], "methods": methods_out,
               "ordering": orderings, "identical_trials": identical, "paper": PAPER}
    summary_path = grid_dir / "summary.json"
    summary_path.write_text(json.dumps(_clean(summary), indent=2))
    report_path = grid_dir / "REPORT.md"
    report_path.write_text("\n".join(lines).rstrip() + "\n")
    return [report_path, summary_path, *written]
