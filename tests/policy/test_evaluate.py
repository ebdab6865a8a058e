"""Evaluation: deterministic actor, JSON keys, the scripted baseline, bad policy files."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from policy.algorithms.td3 import TD3, TD3Config
from policy.shipped import DEFAULT_SHIPPED, SHIPPED, SHIPPED_POLICY, policy_path, shipped_actor
from policy.training.evaluate import ActorController, evaluate


@pytest.fixture(scope="module")
def actor_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("actor") / "actor.pt"
    TD3(TD3Config(seed=1)).save_actor(path)
    return path


def test_eval_writes_json_with_rates_and_intervals(actor_file, tmp_path):
    out = tmp_path / "eval.json"
    s = evaluate(str(actor_file), "valley", 3, seed=7, json_path=out, progress=False)
    data = json.loads(out.read_text())
    for key in ("success_rate", "collision_rate", "timeout_rate", "success_ci95",
                "mean_steps", "mean_path_length"):
        assert key in data
    assert data["success_rate"] + data["collision_rate"] + data["timeout_rate"] == 1.0
    lo, hi = data["success_ci95"]
    assert 0.0 <= lo <= data["success_rate"] <= hi <= 1.0
    # deterministic actor: the same seeds give the same summary
    again = evaluate(str(actor_file), "valley", 3, seed=7, progress=False)
    assert again["mean_steps"] == s["mean_steps"]
    assert again["mean_path_length"] == s["mean_path_length"]


def test_scripted_baseline_is_selectable():
    s = evaluate("scripted", "valley", 2, seed=3, progress=False)
    assert s["episodes"] == 2 and "straight-line" in s["policy"]


def test_bad_policy_files_give_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such policy"):
        ActorController(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"\x00garbage")
    with pytest.raises(ValueError, match=r"not a readable skyloop actor \(not a torch file\)"):
        ActorController(bad)
    with pytest.raises(FileNotFoundError, match="a directory without an actor.pt"):
        ActorController(tmp_path)
    run = tmp_path / "run"
    run.mkdir()
    TD3(TD3Config()).save_actor(run / "actor.pt")
    assert ActorController(run).actor is not None  # a run directory: its actor
    import torch

    state = torch.load(run / "actor.pt", weights_only=True)
    state["actor"]["net.0.weight"] = torch.zeros(400, 50)
    torch.save(state, tmp_path / "shape.pt")
    with pytest.raises(ValueError, match=r"shape.pt: its weights do not fit the 105-400-300-4 "
                                         r"actor .*size mismatch for net.0.weight"):
        ActorController(tmp_path / "shape.pt")


def test_eval_of_a_directory_without_an_actor_is_one_line(tmp_path):
    """``skyloop eval --policy DIR`` (--help promises run directories): a directory
    without an actor.pt is one line naming it, exit 2, before anything flies."""
    out = subprocess.run([sys.executable, "-m", "skyloop", "eval", "--policy", str(tmp_path),
                          "--episodes", "1"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 2, out.stderr[-2000:]
    assert out.stderr.count("\n") == 1 and "Traceback" not in out.stderr, out.stderr
    assert str(tmp_path) in out.stderr and "a directory without an actor.pt" in out.stderr


@pytest.mark.skipif(not SHIPPED_POLICY.exists(), reason="no shipped policy committed yet")
def test_default_is_the_shipped_policy():
    out = subprocess.run([sys.executable, "-m", "skyloop", "eval", "--episodes", "2"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert str(SHIPPED_POLICY) in out.stdout


def test_shipped_policies_by_name(tmp_path):
    """``--policy shipped`` is the default shipped actor, ``shipped:NAME`` one by name
    (each one's folder holds its actor), anything else a path; an unknown name is a
    one-line error naming the flag and the known names."""
    assert policy_path(None) == policy_path("shipped") == SHIPPED_POLICY \
        == shipped_actor(DEFAULT_SHIPPED)
    for name in SHIPPED:
        assert policy_path(f"shipped:{name}").is_file(), name
    assert str(policy_path("runs/x/actor.pt")) == "runs/x/actor.pt"
    with pytest.raises(ValueError, match=r"--policy shipped:nope: no such shipped policy "
                                         r"\(shipped: shipped:valley"):
        policy_path("shipped:nope")
    for command in ("eval", "up", "policy", "demo"):  # up: before any node starts
        episodes = [] if command == "policy" else ["--episodes", "1"]
        out = subprocess.run([sys.executable, "-m", "skyloop", command, "--policy",
                              "shipped:nope", *episodes], capture_output=True, text=True,
                             timeout=300)
        assert out.returncode == 2 and out.stderr.count("\n") == 1, out.stderr[-2000:]
        assert "--policy shipped:nope: no such shipped policy" in out.stderr, command
        assert "started" not in out.stdout, command
    out = subprocess.run([sys.executable, "-m", "skyloop", "learner", "--init-actor",
                          "shipped:nope", "--out", str(tmp_path / "learner")],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and out.stderr.count("\n") == 1, out.stderr[-2000:]
    assert "--init-actor: shipped:nope: no such shipped policy" in out.stderr
    out = subprocess.run([sys.executable, "-m", "skyloop", "eval", "--policy", "shipped:valley",
                          "--episodes", "1"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "shipped TD3+ABR policy 'valley'" in out.stdout
