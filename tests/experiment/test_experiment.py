"""``skyloop experiment``: grid files checked before anything runs; grids on embedded Ray
Tune (real Ray, real trainer); a grid killed mid-run continues to the same CSVs."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from skyloop.experiment.grid import GridError, load_grid

GOOD = """
name = "tiny"
scenario = "valley"
methods = ["td3+tr", "td3+abr"]
seeds = [0, 1]
episodes = 3

[train]
start_steps = 400  # few TD3 updates (from mid-episode 2): the grid is under test
buffer_size = 5000
checkpoint_every = 1
sync = true
"""


def write(tmp_path: Path, text: str, name: str = "grid.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_grid_is_the_product_of_tasks_methods_and_seeds(tmp_path):
    grid = load_grid(write(tmp_path, GOOD))
    assert [t.name for t in grid.trials] == [
        "valley-td3+tr-s0", "valley-td3+abr-s0", "valley-td3+tr-s1", "valley-td3+abr-s1"]
    cfg = grid.trials[1].config
    assert (cfg.algo, cfg.reward, cfg.scenario, cfg.seed, cfg.episodes) == (
        "td3", "abr", "valley", 0, 3)
    assert (cfg.start_steps, cfg.buffer_size, cfg.checkpoint_every) == (400, 5000, 1)
    assert grid.episodes == 12
    crossed = load_grid(write(tmp_path, GOOD.replace(
        'methods = ["td3+tr", "td3+abr"]', 'algos = ["td3", "ddpg"]\nrewards = ["ngr"]')))
    assert {t.method for t in crossed.trials} == {"td3+ngr", "ddpg+ngr"}
    gym = load_grid(write(tmp_path, GOOD.replace(
        'scenario = "valley"', 'env = "BipedalWalkerHardcore-v3"')))
    assert gym.trials[0].config.env == "BipedalWalkerHardcore-v3"


@pytest.mark.parametrize("old, new, field", [
    ('name = "tiny"', 'name = "tiny"\nlearning_rate = 3', "learning_rate"),
    ('"td3+abr"', '"ppo+abr"', "methods: unknown algorithm 'ppo'"),
    ('"td3+abr"', '"td3+xyz"', "methods: unknown reward 'xyz'"),
    ('"td3+abr"', '"td3abr"', "methods: 'td3abr' is not"),
    ('methods = ["td3+tr", "td3+abr"]', "methods = []", "methods: expected a non-empty"),
    ('methods = ["td3+tr", "td3+abr"]', "", "methods: missing"),
    ("seeds = [0, 1]", "seeds = []", "seeds: expected a non-empty"),
    ("seeds = [0, 1]", 'seeds = [0, "one"]', "seeds: 'one' is not"),
    ("seeds = [0, 1]", "seeds = [0, 1.5]", "seeds: 1.5 is not"),
    ("seeds = [0, 1]", "seeds = [1, 1]", "seeds: repeated"),
    ("episodes = 3", "episodes = 0", "episodes: expected a positive integer"),
    ('scenario = "valley"', 'scenario = "moon"', "scenario:"),
    ('scenario = "valley"', 'env = "NoSuchEnv-v9"', "env: unknown Gymnasium env id"),
    ('scenario = "valley"', "", "scenarios: missing"),
    ("start_steps = 400", "start_step = 400", "train.start_step: unknown option"),
    ("start_steps = 400", 'start_steps = "fifty"', "train.start_steps: expected int"),
    ("start_steps = 400", "seed = 3", "train.seed: set it at the top level"),
    ("checkpoint_every = 1", "checkpoint_every = 0", "train.checkpoint_every: must be at least 1"),
    ("start_steps = 400", "start_steps = -1", "train.start_steps: must be 0 or more, got -1"),
    ("episodes = 3", "episodes = 3\nepisodes = 5", "not valid TOML"),
])
def test_a_bad_grid_names_the_file_and_the_field(tmp_path, old, new, field):
    assert old in GOOD
    path = write(tmp_path, GOOD.replace(old, new, 1))
    with pytest.raises(GridError) as err:
        load_grid(path)
    assert str(path) in str(err.value) and field in str(err.value)


REPO = Path(__file__).resolve().parents[2]
COMMITTED_GRIDS = sorted(p.relative_to(REPO) for d in ("experiments", "experiments/general_state",
                                                         "experiments/general_weights")
                         for p in (REPO / d).glob("*.toml"))


@pytest.mark.parametrize("path", COMMITTED_GRIDS, ids=str)
def test_the_committed_grid_files_load_with_one_arithmetic(path):
    """The grid files under experiments/ load as the runner loads them, and each names its
    precision, so that its trials share one arithmetic on any machine (``auto`` would
    follow the machine's bfloat16 units)."""
    grid = load_grid(REPO / path)
    assert grid.trials
    assert len({t.config.precision for t in grid.trials}) == 1
    assert grid.trials[0].config.precision in ("fp32", "bf16")


def test_a_bad_grid_is_a_one_line_cli_error_before_anything_runs(tmp_path):
    path = write(tmp_path, GOOD.replace('"td3+abr"', '"td3+xyz"'))
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "skyloop", "experiment", "run", str(path),
                           "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "unknown reward 'xyz'" in proc.stderr
    assert not out.exists()


def _experiment(grid: Path, out: Path, **popen) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "skyloop", "experiment", "run", str(grid), "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **popen)


def _csvs(out: Path) -> dict[str, bytes]:
    return {p.parent.name: p.read_bytes() for p in sorted(out.glob("*/episodes.csv"))}


def _session_alive(sid: int) -> bool:
    """Whether any process of session ``sid`` (the grid's driver, Ray and its workers) runs."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":  # fields[3]: session id
            return True
    return False


@pytest.fixture(scope="module")
def tiny_grid(tmp_path_factory) -> tuple[Path, Path]:
    """The tiny grid, run once without interruption (2 methods x 2 seeds x 3 episodes)."""
    tmp = tmp_path_factory.mktemp("grid")
    grid = write(tmp, GOOD)
    proc = _experiment(grid, tmp / "out")
    log = proc.communicate(timeout=600)[0]
    assert proc.returncode == 0, log
    (tmp / "run.log").write_text(log)
    return grid, tmp / "out"


def test_a_tiny_grid_runs_on_embedded_ray_and_a_rerun_skips_it(tiny_grid):
    grid, out = tiny_grid
    csvs = _csvs(out)
    # progress: a line as each trial finishes, with the rates since the command began
    lines = [x for x in (out.parent / "run.log").read_text().splitlines() if "(finished " in x]
    assert len(lines) == 4 and lines[-1].startswith("[experiment] 4/4 trials finished, "
                                                    "episodes 12/12 (100%)"), lines
    assert all(re.search(r"[1-9][\d,]* env steps/s, ETA", x) for x in lines), lines
    assert sorted(csvs) == sorted(t.name for t in load_grid(grid).trials)
    for name, data in csvs.items():
        assert len(data.splitlines()) == 1 + 3, name
        assert (out / name / "result.json").is_file() and (out / name / "actor.pt").is_file()
    proc = subprocess.run([sys.executable, "-m", "skyloop", "experiment", "run", str(grid),
                           "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "4 finished, 0 to run" in proc.stdout
    assert _csvs(out) == csvs


def test_a_grid_killed_mid_run_continues_to_the_same_csvs(tiny_grid, tmp_path):
    """The tiny grid's seed-0 trials (2 x 3 episodes), killed and continued: the same CSVs
    as those trials of the uninterrupted grid."""
    _, reference = tiny_grid
    grid = write(tmp_path, GOOD.replace("seeds = [0, 1]", "seeds = [0]"))
    out = tmp_path / "out"
    proc = _experiment(grid, out, start_new_session=True)  # its own session, like a terminal
    deadline = time.monotonic() + 300
    while True:  # kill once a trial has checkpointed, before the grid is done
        rows = sum(len(d.splitlines()) - 1 for d in _csvs(out).values())
        if list(out.glob("*/checkpoint.pt")) and 2 <= rows < 6:
            break
        assert proc.poll() is None and time.monotonic() < deadline, "grid ended too soon"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.communicate()
    deadline = time.monotonic() + 30
    while _session_alive(proc.pid):  # Ray's processes die with the driver
        assert time.monotonic() < deadline, "Ray processes outlived the killed grid"
        time.sleep(0.2)
    assert any(not (p / "result.json").exists() for p in out.iterdir() if p.is_dir())

    rerun = _experiment(grid, out)
    log = rerun.communicate(timeout=600)[0]
    assert rerun.returncode == 0, log
    ran = _csvs(out)  # --sync trials: as if never interrupted
    assert sorted(ran) == ["valley-td3+abr-s0", "valley-td3+tr-s0"]
    assert ran == {name: data for name, data in _csvs(reference).items() if name in ran}


def test_the_report_of_a_tiny_grid_has_every_trial_and_method(tiny_grid):
    import json

    _, out = tiny_grid
    proc = subprocess.run([sys.executable, "-m", "skyloop", "experiment", "report", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    trials = {t["trial"]: t for t in summary["trials"]}
    assert sorted(trials) == sorted(_csvs(out))
    for name, t in trials.items():
        rows = (out / name / "episodes.csv").read_text().splitlines()[1:]
        outcomes = [r.split(",")[3] for r in rows]
        assert t["finished"] and t["episodes"] == len(rows) == 3
        assert t["success_last500"] == pytest.approx(outcomes.count("success") / len(rows))
        assert t["env_steps"] == int(rows[-1].split(",")[6])
    assert {m["method"] for m in summary["methods"]} == {"td3+tr", "td3+abr"}
    report = (out / "REPORT.md").read_text()
    assert "valley-td3+abr-s1" in report and (out / "curves_valley.png").stat().st_size > 1000
