"""``skyloop experiment report``: numbers recomputed here from synthetic CSVs (success over
the last 500, t-intervals, the ordering, env returns), partial and empty grids, figures,
and the held-out evaluation of real tiny trials with its cache."""

from __future__ import annotations

import csv
import json
from collections import deque
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from policy.training.train import CSV_FIELDS, TrainConfig, Trainer
from skyloop.experiment.grid import load_grid
from skyloop.experiment.report import (
    aggregate,
    identical_pairs,
    t_interval,
    trailing_mean,
    write_report,
)

GRID = """
name = "synthetic"
{task}
methods = {methods}
seeds = [0, 1]
episodes = {episodes}

[train]
checkpoint_every = 100
{train}
"""
TRIAL_KEYS = {"trial", "algo", "reward", "env", "seed", "episodes", "episodes_planned",
              "finished", "success_last500", "collision_last500", "return_last100",
              "env_steps", "wall_s"}
DIAGNOSTICS = ["base_return", "r_progress", "r_altitude", "r_heading", "r_velocity_heading",
               "r_collision", "abr_patterns", "abr_new_patterns", "abr_groups"]


def synthetic_rows(p_success: float, n: int, seed: int, reward: str) -> list[dict]:
    """``n`` CSV rows with outcomes drawn from a seeded RNG; window rates by a deque."""
    rng = np.random.default_rng(seed)
    p_coll = (1 - p_success) / 2
    outcomes = rng.choice(["success", "collision", "timeout"], size=n,
                          p=[p_success, p_coll, 1 - p_success - p_coll])
    window: deque[str] = deque(maxlen=500)
    rows, total, patterns = [], 0, 0
    for i, outcome in enumerate(outcomes):
        window.append(outcome)
        steps = {"success": int(rng.integers(100, 250)), "collision": int(rng.integers(20, 90)),
                 "timeout": 300}[outcome]
        total += steps
        terms = {"r_progress": rng.normal(10, 3), "r_altitude": rng.normal(-300, 40),
                 "r_heading": rng.normal(60, 5), "r_velocity_heading": rng.normal(30, 5),
                 "r_collision": -50.0 if outcome == "collision" else 0.0}
        base = sum(terms.values())
        groups = new = 0
        bonus = 0.0
        if outcome == "success":
            if reward in ("tr", "egr"):
                bonus = 50.0 if reward == "tr" else float(steps)
            elif reward == "abr":
                groups = steps // 3
                new = int(rng.integers(0, groups // 4 + 1))
                patterns += new
                bonus = float(rng.uniform(0, 80))
        rows.append({"episode": i + 1, "return": base + bonus, "steps": steps,
                     "outcome": outcome,
                     "success_rate_500": window.count("success") / len(window),
                     "collision_rate_500": window.count("collision") / len(window),
                     "total_steps": total, "base_return": base, **terms,
                     "abr_patterns": patterns, "abr_new_patterns": new, "abr_groups": groups})
    return rows


def write_csv(path: Path, rows: list[dict], fields: list[str] = CSV_FIELDS) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def make_grid(root: Path, p: dict[str, float], episodes: int = 600,
              task: str = 'scenario = "valley"', train: str = "",
              done: dict[str, int] | None = None,
              ) -> tuple[Path, dict[str, list[dict]]]:
    """A grid directory like ``experiment run`` leaves; ``done`` trial -> episodes so far
    (missing: all; -1: no directory). Returns the dir and each trial's rows."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "grid.toml").write_text(GRID.format(task=task, episodes=episodes, train=train,
                                                methods=json.dumps(list(p))))
    (root / "runs.json").write_text(json.dumps([
        {"commit": "a" * 40, "started": "x", "python": "3.11", "trials_to_run": []},
        {"commit": "b" * 40, "started": "y", "python": "3.11", "trials_to_run": []}]))
    grid = load_grid(root / "grid.toml")
    data = {}
    for k, trial in enumerate(grid.trials):
        n = (done or {}).get(trial.name, episodes)
        if n < 0:
            continue
        rows = synthetic_rows(p[trial.method], n, seed=100 + k, reward=trial.config.reward)
        data[trial.name] = rows
        run = root / trial.name
        write_csv(run / "episodes.csv", rows)
        (run / "config.json").write_text(json.dumps(asdict(trial.config)))
        if n >= episodes:
            (run / "result.json").write_text(json.dumps(
                {"episodes": n, "total_steps": rows[-1]["total_steps"], "wall_s": 60.0 + k}))
    return root, data


def load(root: Path) -> tuple[dict, str]:
    return json.loads((root / "summary.json").read_text()), (root / "REPORT.md").read_text()


def test_window_and_interval_helpers():
    x = np.random.default_rng(0).random(1200) < 0.4
    window: deque[bool] = deque(maxlen=500)
    expected = []
    for v in x:
        window.append(bool(v))
        expected.append(sum(window) / len(window))
    np.testing.assert_allclose(trailing_mean(x, 500), expected, atol=1e-12)
    assert t_interval([0.4]) == (0.4, None, None)  # one seed: undefined, no crash
    assert t_interval([])[1:] == (None, None)
    assert t_interval([0.3, 0.3]) == (0.3, 0.3, 0.3)
    # two seeds' success rates: the t-interval passes 100%; a rate's is clipped to [0, 1]
    free, rate = aggregate({0: 0.832, 1: 0.906}), aggregate({0: 0.832, 1: 0.906}, rate=True)
    assert free["hi"] > 1.0 and free["lo"] < 0.5
    assert (rate["lo"], rate["hi"]) == (pytest.approx(free["lo"]), 1.0)
    assert aggregate({0: 0.01, 1: 0.09}, rate=True)["lo"] == 0.0


def test_report_numbers_are_the_csvs(tmp_path):
    root, data = make_grid(tmp_path / "g", {"td3+tr": 0.3, "td3+abr": 0.6})
    paths = write_report(root)
    summary, report = load(root)
    assert {"grid", "commits", "trials", "methods"} <= set(summary)
    assert summary["grid"] == "synthetic" and summary["commits"] == ["a" * 40, "b" * 40]
    by_trial = {t["trial"]: t for t in summary["trials"]}
    assert len(by_trial) == 4
    for name, rows in data.items():
        t = by_trial[name]
        assert TRIAL_KEYS <= set(t)
        outcomes = np.array([r["outcome"] for r in rows])
        assert t["success_last500"] == pytest.approx(np.mean(outcomes[-500:] == "success"))
        assert t["collision_last500"] == pytest.approx(np.mean(outcomes[-500:] == "collision"))
        peak = max(r["success_rate_500"] for r in rows[499:])
        assert t["peak_success500"] == pytest.approx(peak)
        assert t["return_last100"] == pytest.approx(np.mean([r["base_return"]
                                                             for r in rows[-100:]]))
        assert t["env_steps"] == sum(r["steps"] for r in rows)
        assert t["finished"] and t["episodes"] == t["episodes_planned"] == 600
        assert t["wall_s"] is not None
    for m in summary["methods"]:
        assert {"task", "method", "n_seeds"} <= set(m) and m["n_seeds"] == 2
        values = [by_trial[f"valley-{m['method']}-s{s}"]["success_last500"] for s in (0, 1)]
        lo, hi = stats.t.interval(0.95, 1, loc=np.mean(values), scale=stats.sem(values))
        agg = m["success_last500"]
        assert agg["values"] == pytest.approx(values)
        assert (agg["mean"], agg["lo"], agg["hi"]) == pytest.approx((np.mean(values), lo, hi))
        for key in ("collision_last500", "peak_success500", "env_steps", "wall_s"):
            assert {"mean", "lo", "hi", "values"} <= set(m[key])
    abr = next(m for m in summary["methods"] if m["method"] == "td3+abr")
    abr_rows = [r for s in (0, 1) for r in data[f"valley-td3+abr-s{s}"]]
    first = [r for s in (0, 1) for r in data[f"valley-td3+abr-s{s}"][:500]]
    block = abr["abr"]["blocks"][0]
    assert block["new_share"] == pytest.approx(sum(r["abr_new_patterns"] for r in first)
                                               / sum(r["abr_groups"] for r in first))
    bonus = [r["return"] - r["base_return"] for r in abr_rows if r["outcome"] == "success"]
    assert abr["goal_bonus"]["bonus"]["q50"] == pytest.approx(np.median(bonus))
    assert "Trials finished: **4/4**" in report and "84.8%" in report and "42.2%" in report
    assert "experiment report" in report and "--eval-episodes 200" in report
    assert "`checkpoint_every = 100`" in report and "`episodes = 600`" in report
    assert "a" * 40 in report and "b" * 40 in report
    pngs = [p for p in paths if p.suffix == ".png"]
    assert {p.name for p in pngs} == {"curves_valley.png", "bonus_valley.png"}
    assert all(p.stat().st_size > 1000 for p in pngs)


@pytest.mark.parametrize("p_abr, p_tr, holds", [(0.7, 0.2, True), (0.2, 0.7, False)])
def test_the_ordering_statement_follows_the_data(tmp_path, p_abr, p_tr, holds):
    root, _ = make_grid(tmp_path / "g", {"td3+tr": p_tr, "td3+abr": p_abr})
    write_report(root)
    summary, report = load(root)
    o = summary["ordering"]["valley"]["training"]
    assert o["paper"] == ["td3+abr", "td3+tr"]
    assert o["ours"] == (["td3+abr", "td3+tr"] if holds else ["td3+tr", "td3+abr"])
    (pair,) = o["pairs"]
    assert pair["holds"] is holds and (pair["gap"] > 0) is holds
    assert pair["intervals_overlap"] is False  # 0.7 vs 0.2 over 500 episodes: far apart
    line = next(x for x in report.splitlines() if x.startswith("| td3+abr > td3+tr"))
    assert ("| holds |" in line) is holds and ("does NOT hold" in line) is not holds
    assert "do not overlap" in line


def test_a_partial_grid_reports_what_it_has(tmp_path):
    root, _ = make_grid(tmp_path / "g", {"td3+tr": 0.3, "td3+abr": 0.6},
                        done={"valley-td3+tr-s1": 300, "valley-td3+abr-s1": -1})
    with (root / "valley-td3+tr-s1" / "episodes.csv").open("a") as f:
        f.write("301,-12.5,40,coll")  # a row being written: no newline yet
    write_report(root)
    summary, report = load(root)
    by_trial = {t["trial"]: t for t in summary["trials"]}
    unfinished = by_trial["valley-td3+tr-s1"]
    assert unfinished["status"] == "unfinished" and not unfinished["finished"]
    assert unfinished["episodes"] == 300 and unfinished["wall_s"] is None
    assert unfinished["peak_success500"] is None  # fewer than 500 episodes
    assert by_trial["valley-td3+abr-s1"]["status"] == "not started"
    assert "Trials finished: **2/4**" in report
    assert "unfinished: 300/600 episodes (50%)" in report
    assert "Unfinished or not started: valley-td3+tr-s1, valley-td3+abr-s1." in report
    assert "(n=1)" in report  # td3+abr has one seed: no interval
    abr = next(m for m in summary["methods"] if m["method"] == "td3+abr")
    assert abr["n_seeds"] == 1 and abr["success_last500"]["lo"] is None
    assert "partial: some seeds unfinished" in report


def test_empty_and_old_csvs_do_not_crash(tmp_path):
    root, data = make_grid(tmp_path / "g", {"td3+tr": 0.3, "td3+abr": 0.6}, episodes=50)
    (root / "valley-td3+tr-s0" / "episodes.csv").write_text("")
    (root / "valley-td3+tr-s0" / "result.json").unlink()
    (root / "valley-td3+tr-s1" / "episodes.csv").write_text(",".join(CSV_FIELDS) + "\r\n")
    (root / "valley-td3+tr-s1" / "result.json").unlink()
    old = [k for k in CSV_FIELDS if k not in DIAGNOSTICS]  # a CSV from before the diagnostics
    write_csv(root / "valley-td3+abr-s0" / "episodes.csv", data["valley-td3+abr-s0"], old)
    paths = write_report(root)
    summary, report = load(root)
    by_trial = {t["trial"]: t for t in summary["trials"]}
    for name in ("valley-td3+tr-s0", "valley-td3+tr-s1"):
        assert by_trial[name]["status"] == "no episodes" and by_trial[name]["episodes"] == 0
        assert by_trial[name]["success_last500"] is None
    assert report.count("no episodes (empty CSV)") == 2
    assert "No episodes yet (left out below): td3+tr." in report
    older = by_trial["valley-td3+abr-s0"]
    outcomes = np.array([r["outcome"] for r in data["valley-td3+abr-s0"]])
    assert older["success_last500"] == pytest.approx(np.mean(outcomes == "success"))
    assert older["return_last100"] is None and older["reward_terms"] is None
    assert all(p.is_file() and p.stat().st_size > 0 for p in paths)


def test_a_gym_env_reports_the_env_return(tmp_path):
    root, data = make_grid(tmp_path / "g", {"td3+ngr": 0.1, "td3+abr": 0.2}, episodes=300,
                           task='env = "BipedalWalkerHardcore-v3"', train="goal_return = 0.0")
    paths = write_report(root)
    summary, report = load(root)
    by_trial = {t["trial"]: t for t in summary["trials"]}
    for name, rows in data.items():
        assert by_trial[name]["env"] == "BipedalWalkerHardcore-v3"
        assert by_trial[name]["return_last100"] == pytest.approx(
            np.mean([r["base_return"] for r in rows[-100:]]))
        best = max(range(len(rows)), key=lambda i: rows[i]["base_return"])
        assert by_trial[name]["best_return"] == pytest.approx(rows[best]["base_return"])
        assert by_trial[name]["best_return_episode"] == best + 1
        assert f"(episode {best + 1:,})" in report
    o = summary["ordering"]["BipedalWalkerHardcore-v3"]["training"]
    assert o["metric"] == "return_last100" and o["paper"] == ["td3+abr", "td3+ngr"]
    means = {m["method"]: m["return_last100"]["mean"] for m in summary["methods"]}
    assert o["ours"] == sorted(means, key=lambda m: -means[m])
    assert "-70.91" in report and "-89.61" in report
    assert (root / "curves_BipedalWalkerHardcore-v3.png").stat().st_size > 1000
    assert root / "curves_BipedalWalkerHardcore-v3.png" in paths


def _one_trial_grid(root: Path, task: str, method: str, train: str, episodes: int = 2) -> Path:
    root.mkdir(parents=True)
    (root / "grid.toml").write_text(f'name = "tiny"\n{task}\nmethods = ["{method}"]\n'
                                    f"seeds = [0]\nepisodes = {episodes}\n\n[train]\n{train}\n")
    return root


def test_eval_of_a_real_trial_is_cached(tmp_path):
    root = _one_trial_grid(tmp_path / "g", 'scenario = "valley"', "td3+abr",
                           "start_steps = 50\nbuffer_size = 5000")
    run = root / "valley-td3+abr-s0"
    Trainer(TrainConfig(episodes=2, start_steps=50, buffer_size=5000, progress=False),
            run).run()
    write_report(root, eval_episodes=2)
    cache = run / "eval_2.json"
    ev = json.loads(cache.read_text())
    assert ev["episodes"] == 2 and ev["seed"] == 1_000_000_000 and ev["deterministic"]
    summary, report = load(root)
    (trial,) = summary["trials"]
    assert trial["finished"] and trial["eval_success"] == ev["success_rate"]
    assert trial["eval_success_ci95"] == ev["success_ci95"]
    assert trial["eval"]["actor_sha256"] == ev["actor_sha256"]
    (method,) = summary["methods"]
    assert method["eval_success"]["values"] == [ev["success_rate"]]
    assert "Held-out evaluation (2 episodes per trial)" in report
    assert "Every started trial's `config.json` matches the grid." in report
    with (run / "episodes.csv").open() as f:  # the report's window is the trainer's
        rows = list(csv.DictReader(f))
    np.testing.assert_allclose(
        trailing_mean([r["outcome"] == "success" for r in rows], 500),
        [float(r["success_rate_500"]) for r in rows], atol=1e-6)
    mtime = cache.stat().st_mtime_ns
    write_report(root, eval_episodes=2)
    assert cache.stat().st_mtime_ns == mtime  # reused, not recomputed


def test_eval_of_a_real_gym_trial(tmp_path):
    # one 200-step episode, all of it random actions (no updates): quick, and a real actor
    root = _one_trial_grid(tmp_path / "g", 'env = "Pendulum-v1"', "td3+ngr",
                           "start_steps = 1000\nbuffer_size = 5000\ngoal_return = -1000.0",
                           episodes=1)
    run = root / "Pendulum-v1-td3+ngr-s0"
    Trainer(TrainConfig(env="Pendulum-v1", reward="ngr", episodes=1, start_steps=1000,
                        buffer_size=5000, goal_return=-1000.0, progress=False), run).run()
    write_report(root, eval_episodes=2)
    ev = json.loads((run / "eval_2.json").read_text())
    assert ev["env"] == "Pendulum-v1" and ev["episodes"] == 2 and ev["mean_steps"] == 200
    assert ev["mean_return"] < 0 and 0 <= ev["success_rate"] <= 1
    summary, _ = load(root)
    assert summary["trials"][0]["eval_return"] == ev["mean_return"]
    assert summary["methods"][0]["eval_return"]["mean"] == ev["mean_return"]


def test_identical_pairs_finds_a_method_that_never_acted():
    rng = np.random.default_rng(0)
    ret = rng.normal(-50.0, 10.0, 40)
    steps = rng.integers(50, 2000, 40)
    base = {"return": ret, "steps": steps, "total_steps": np.cumsum(steps)}
    differs = {**base, "return": np.where(np.arange(40) == 39, ret + 0.5, ret)}  # last row
    shorter = {k: v[:39] for k, v in base.items()}  # the same so far: a trial further on
    pairs = identical_pairs({
        "td3+ngr": {0: base, 1: base, 2: base, 3: {k: v[:0] for k, v in base.items()}},
        "td3+abr": {0: dict(base), 1: differs, 2: shorter, 3: {k: v[:0] for k, v in base.items()}},
    })
    assert pairs == [{"methods": ["td3+ngr", "td3+abr"], "seed": 0, "episodes": 40, "of": [40, 40]},
                     {"methods": ["td3+ngr", "td3+abr"], "seed": 2, "episodes": 39, "of": [40, 39]}]
