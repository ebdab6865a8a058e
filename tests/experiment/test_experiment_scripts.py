"""The scripts beside the grids (experiments/general/ship.py, pick_by_validation.py,
experiments/paper_bipedal/goal_thresholds.py): bad input is one line naming what is
wrong, before anything is evaluated or written."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
GENERAL = ROOT / "experiments" / "general"


def run(script: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(script), *args], cwd=script.parent,
                          capture_output=True, text=True, timeout=120)


def last_line(proc: subprocess.CompletedProcess) -> str:
    return proc.stderr.strip().splitlines()[-1]


def test_ship_refuses_a_missing_grid_a_shipped_folder_and_a_zero_count(tmp_path):
    proc = run(GENERAL / "ship.py", str(tmp_path / "nope"))
    assert proc.returncode == 2 and "nope: no such directory" in last_line(proc)
    shipped = ROOT / "policy" / "shipped" / "td3_abr_valley"
    before = (shipped / "actor.pt").read_bytes()
    proc = run(GENERAL / "ship.py", str(tmp_path), "--out", str(shipped))
    assert proc.returncode == 2 and "already a shipped policy" in last_line(proc)
    assert (shipped / "actor.pt").read_bytes() == before
    for flag in ("--worlds", "--episodes", "--heldout-worlds", "--heldout-episodes"):
        proc = run(GENERAL / "ship.py", str(tmp_path), flag, "0")
        assert proc.returncode == 2, flag
        assert f"argument {flag}: expected a positive integer, got 0" in last_line(proc)
    proc = run(GENERAL / "ship.py", str(tmp_path))  # a directory without finished trials
    assert proc.returncode == 1 and "no finished trial" in last_line(proc)


def test_pick_by_validation_refuses_what_is_not_a_run(tmp_path):
    proc = run(GENERAL / "pick_by_validation.py", str(tmp_path), "--worlds", "3")
    assert proc.returncode == 1 and "not a training run (no episodes.csv)" in last_line(proc)


def test_goal_thresholds_names_a_csv_without_its_columns_and_skips_an_empty_trial(tmp_path):
    script = ROOT / "experiments" / "paper_bipedal" / "goal_thresholds.py"
    empty = tmp_path / "Bipedal-td3+ngr-s0"
    empty.mkdir()
    (empty / "episodes.csv").write_text("episode,return,steps,base_return\n")
    full = tmp_path / "Bipedal-td3+ngr-s1"
    full.mkdir()
    (full / "episodes.csv").write_text(
        "episode,return,steps,base_return\n1,-100,90,-100\n2,-50,2000,-50\n")
    proc = run(script, str(tmp_path), "--thresholds", "-60")
    assert proc.returncode == 0, proc.stderr
    assert "Bipedal-td3+ngr-s0: no episode yet, left out" in proc.stdout
    assert "| 1 | 2 | -50.0 | 50.0% (first ep 2, 1 timeouts) |" in proc.stdout
    (full / "episodes.csv").write_text("episode,return\n1,-100\n")
    proc = run(script, str(tmp_path))
    assert proc.returncode == 1
    assert last_line(proc) == f"{full / 'episodes.csv'}: no column base_return, steps"


def test_the_pick_is_the_actor_file_of_the_run_as_it_is_now(tmp_path, monkeypatch):
    """Rows of selection.jsonl may name an actor where the run once was (a worktree since
    removed); the pick names the run's own file, and refuses a snapshot that is gone."""
    monkeypatch.syspath_prepend(str(GENERAL))
    from pick_by_validation import GOALS, pick

    run = tmp_path / "mix-td3+abr-s0"
    (run / "snapshots").mkdir(parents=True)
    (run / "episodes.csv").write_text("episode\n" + "".join(f"{i}\n" for i in range(1, 201)))
    (run / "result.json").write_text("{}")
    for name in ("snapshots/actor-ep100.pt", "actor.pt"):
        (run / name).write_bytes(b"")
    rows = [{"episode": e, "family": f, "actor": f"/gone/actor-ep{e}.pt",
             "success": rate if f == "city" else 0.95}
            for e, rate in ((100, 0.90), (200, 0.80)) for f in GOALS]
    choice = pick(run, rows, episodes=60, worlds=20)
    assert choice["episode"] == 100 and choice["margin"] == pytest.approx(0.05)
    assert choice["actor"] == str(run / "snapshots" / "actor-ep100.pt")
    (run / "snapshots" / "actor-ep100.pt").unlink()
    with pytest.raises(SystemExit, match="the actor of episode 100 is gone"):
        pick(run, rows, episodes=60, worlds=20)


def test_the_final_round_has_the_last_word(tmp_path, monkeypatch):
    """Successive halving (pick_by_validation.screened) with the validation flights replaced
    by a table of rates: the screen passes the 2 best of 3 actors on, the full round the
    best of those to the final round, and the pick is made on the final round's rates
    even where the full round ranked the actors otherwise."""
    monkeypatch.syspath_prepend(str(GENERAL))
    import pick_by_validation as pbv

    # success per (round's episodes, actor's training episode)
    rates = {20: {100: 0.95, 200: 0.95, 300: 0.50},
             60: {100: 0.97, 200: 0.93, 300: 0.50},
             200: {100: 0.86, 200: 0.92, 300: 0.50}}
    flown = []

    def validate(run, episodes, worlds, only=None):
        chosen = sorted(rates[episodes] if only is None else only)
        flown.append((episodes, chosen))
        return [{"episode": e, "family": f, "success": rates[episodes][e]}
                for e in chosen for f in pbv.GOALS]

    monkeypatch.setattr(pbv, "validate", validate)
    run = tmp_path / "mix-td3+abr-s0"
    (run / "snapshots").mkdir(parents=True)
    (run / "episodes.csv").write_text("episode\n" + "".join(f"{i}\n" for i in range(1, 301)))
    for e in (100, 200, 300):
        (run / "snapshots" / f"actor-ep{e}.pt").write_bytes(b"")
    seen, rows = pbv.screened(run, 60, 20, screen=20, keep=2, final=200, final_keep=2)
    assert flown == [(20, [100, 200, 300]), (60, [100, 200]), (200, [100, 200])]
    assert {r["episode"] for r in seen} == {100, 200, 300}
    choice = pbv.pick(run, rows, 200, 20)
    assert choice["episode"] == 200 and choice["episodes_per_family"] == 200
    flown.clear()
    _, rows = pbv.screened(run, 60, 20, screen=20, keep=2, final=0)  # no final round
    assert flown == [(20, [100, 200, 300]), (60, [100, 200])]
    assert pbv.pick(run, rows, 60, 20)["episode"] == 100


def test_ship_validates_trials_in_parallel_and_screens_before_the_full_count(tmp_path):
    """Two finished "trials" holding the shipped actor twice each, validated two at a time
    (real flights on validation worlds): every actor on the screen's episodes, only the
    best one on the full count, that one again on the final count, and the grid's pick
    among those, made on the final count."""
    import json
    import shutil

    from policy.shipped import SHIPPED_POLICY

    grid = tmp_path / "grid"
    for name in ("mix-td3+abr-s0", "mix-td3+tr-s0"):
        trial = grid / name
        (trial / "snapshots").mkdir(parents=True)
        (trial / "episodes.csv").write_text("episode\n1\n2\n")
        (trial / "result.json").write_text("{}")
        shutil.copyfile(SHIPPED_POLICY, trial / "snapshots" / "actor-ep1.pt")
        shutil.copyfile(SHIPPED_POLICY, trial / "actor.pt")
    flags = ["--episodes", "2", "--worlds", "1", "--screen", "1", "--keep", "1",
             "--final", "3", "--final-keep", "1"]
    proc = run(GENERAL / "ship.py", str(grid), *flags, "--jobs", "2")
    assert proc.returncode == 0, proc.stderr[-3000:]
    selection = json.loads((grid / "selection.json").read_text())
    assert len(selection["trials"]) == 2
    logs = {}
    for trial in selection["trials"]:
        log = Path(trial["run"]) / "selection.jsonl"
        rows = [json.loads(x) for x in log.open()]
        logs[log] = len(rows)
        screen = [r for r in rows if r["episodes"] == 1]
        full = [r for r in rows if r["episodes"] == 2]
        assert sorted({r["episode"] for r in screen}) == [1, 2] and len(screen) == 8
        final = [r for r in rows if r["episodes"] == 3]
        assert len({r["episode"] for r in full}) == 1 and len(full) == 4
        assert {r["episode"] for r in final} == {trial["episode"]} and len(final) == 4
        assert trial["episodes_per_family"] == 3
        assert (Path(trial["run"]) / "validation.png").stat().st_size > 1000
    assert selection["pick"] == selection["trials"][0]  # the same actor: earliest on ties
    again = run(GENERAL / "ship.py", str(grid), *flags)  # resumable: nothing flown again
    assert again.returncode == 0, again.stderr[-3000:]
    assert {log: sum(1 for _ in log.open()) for log in logs} == logs


def test_average_actors_is_the_mean_of_the_kept_weights_and_refuses_a_mismatch(tmp_path):
    """experiments/general/average_actors.py: the shipped actor and a copy with weights
    doubled average to 1.5x the shipped weights, and load as an actor; a range with one
    actor, or actors of another shape, is a one-line error."""
    import torch

    from policy.algorithms.td3 import load_actor
    from policy.shipped import SHIPPED_POLICY

    run_dir = tmp_path / "mix-td3+tr-s0"
    (run_dir / "snapshots").mkdir(parents=True)
    (run_dir / "episodes.csv").write_text("episode\n1\n")
    state = torch.load(SHIPPED_POLICY, map_location="cpu", weights_only=True)
    torch.save(state, run_dir / "snapshots" / "actor-ep100.pt")
    doubled = {**state, "actor": {k: 2 * v for k, v in state["actor"].items()}}
    torch.save(doubled, run_dir / "snapshots" / "actor-ep200.pt")
    out = tmp_path / "mean.pt"
    script = GENERAL / "average_actors.py"
    proc = run(script, str(run_dir), "--first", "100", "--last", "200", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    mean = load_actor(out)
    for name, value in mean.state_dict().items():
        assert torch.allclose(value, 1.5 * state["actor"][name].float()), name
    proc = run(script, str(run_dir), "--first", "150", "--last", "200", "--out", str(out))
    assert proc.returncode == 2 and "1 kept actor(s)" in last_line(proc)
    other = {**state, "config": {**state["config"], "hidden": [64, 64]}}
    torch.save(other, run_dir / "snapshots" / "actor-ep200.pt")
    proc = run(script, str(run_dir), "--first", "100", "--last", "200", "--out", str(out))
    assert proc.returncode == 2 and "actor-ep100.pt: its config differs" in last_line(proc)


def test_ship_table_holds_a_family_worse_only_when_the_test_says_so(monkeypatch):
    """The held-out table's rule: each family at its goal and not below the valley policy
    at one-sided p < 0.05 (Fisher's exact test on 200 episodes each)."""
    import json

    monkeypatch.syspath_prepend(str(GENERAL))
    from ship import GOALS, table, worse_p

    base = {f: json.loads((GENERAL / f"baseline-valley-policy-{f}.json").read_text())
            for f in GOALS}

    def result(rate: float) -> dict:
        return {"success_rate": rate, "collision_rate": 0.0, "timeout_rate": 1 - rate,
                "success_ci95": [rate - 0.04, rate + 0.03], "episodes": 200}

    assert base["valley"]["success_rate"] == 0.93 and base["valley"]["episodes"] == 200
    assert worse_p(result(0.915), base["valley"]) > 0.05  # 183 of 200 against 186
    assert worse_p(result(0.85), base["valley"]) < 0.05  # 170 against 186
    near = {f: result(0.915) for f in GOALS}
    text, met = table(near)
    assert met and "| valley | 91.5% (87.5%-94.5%) |" in text and "-1.5% (p " in text
    text, met = table({**near, "dynamic": result(0.80)})
    assert not met and text.count("**not met**") == 1
    text, met = table({**near, "city": result(0.84)})  # below the city goal of 85%
    assert not met and "| city | 84.0%" in text


def test_altitude_probe_counts_flights_over_raised_ground_and_names_a_bad_actor(tmp_path,
                                                                                monkeypatch):
    """experiments/general/altitude_probe.py: its summary counts an episode as "over" only
    where the ground under the path rose above the flight level + 1 m; a real flight of the
    shipped actor gives rows in range; an actor without a label is a one-line error."""
    monkeypatch.syspath_prepend(str(GENERAL))
    from altitude_probe import fly, summary

    rows = [{"outcome": "success", "max_altitude": 8.0, "max_ground_under": 5.0},
            {"outcome": "timeout", "max_altitude": 4.0, "max_ground_under": 4.4},
            {"outcome": "success", "max_altitude": 5.0, "max_ground_under": 1.0}]
    s = summary(rows, flight_level=3.5)
    assert s["flew_over_raised_ground"] == pytest.approx(1 / 3)
    assert s["success"] == pytest.approx(2 / 3) and s["timeout"] == pytest.approx(1 / 3)
    assert s["above_6m"] == pytest.approx(1 / 3) and s["max_altitude_median"] == 5.0
    flown = fly("shipped:valley", "valley", worlds=1, episodes=1)
    assert len(flown) == 1 and flown[0]["outcome"] in ("success", "collision", "timeout")
    assert 0.0 < flown[0]["max_altitude"] < 30.0
    proc = run(GENERAL / "altitude_probe.py", "shipped:valley")
    assert proc.returncode == 2
    assert "actor 'shipped:valley': expected LABEL=ACTOR" in last_line(proc)
