"""The state-design options end to end (issue 14): an actor trained with ``--encoding
proximity`` flies the stack when perception makes its observations that way (``skyloop up``
does by itself, or with ``--encoding proximity``), and holds, counted and said in the
summary, when told to make them the default way; an actor trained with a 6 m icosahedron
and 5 frames a state flies ``skyloop up`` with no flag at all (the launcher sets
SKY_ICO_RADIUS, which the LiDAR's range follows, and the policy stacks 5 frames). Real
processes on loopback."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from loopback import free_port

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def proximity_actor(tmp_path_factory) -> Path:
    from policy.training.train import TrainConfig, Trainer

    out = tmp_path_factory.mktemp("prox")
    Trainer(TrainConfig(episodes=2, encoding="proximity", sync=True, start_steps=50,
                        buffer_size=5000, seed=1, progress=False), out).run()
    return out / "actor.pt"


def _up(actor: Path, json_path: Path, *extra: str) -> subprocess.CompletedProcess:
    udp = [free_port(socket.SOCK_DGRAM) for _ in range(4)]
    cmd = [sys.executable, "-m", "skyloop", "up", "--hub", f"tcp/127.0.0.1:{free_port()}",
           "--api-port", str(udp[0]), "--api-local-port", str(udp[1]),
           "--gcs-port", str(udp[2]), "--gcs-local-port", str(udp[3]),
           "--policy", str(actor), "--episodes", "1", "--max-steps", "15", "--lockstep",
           "--lockstep-timeout", "5", "--json", str(json_path), *extra]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("encoding", [None, "proximity", "distance"])
def test_the_policy_flies_only_observations_made_as_trained(proximity_actor, tmp_path,
                                                           encoding):
    flags = [] if encoding is None else ["--encoding", encoding]
    proc = _up(proximity_actor, tmp_path / "s.json", *flags)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    policy = json.loads((tmp_path / "s.json").read_text())["counters"]["policy"]
    if encoding is None:  # the launcher made the state as trained, and said so
        assert "in the state it was trained on: proximity encoding" in proc.stdout
    if encoding in (None, "proximity"):  # as trained: every step answered
        assert policy["refusals"] == 0 and policy["sent"] >= 15, policy
        assert "the policy held the vehicle" not in proc.stdout
    else:  # perception's default encoding: held from the first observation, and said
        assert policy["refusals"] == 1 and policy["sent"] == 0, policy
        assert "the policy held the vehicle 1 time(s)" in proc.stdout


def test_an_actor_of_another_radius_and_frames_flies_the_stack_as_trained(tmp_path):
    """A 6 m icosahedron (the LiDAR at 6.5 m) and 5 frames a state, trained in-process for
    two episodes: ``skyloop up --policy ACTOR`` and nothing else answers every step (no
    hold for an off-task SKY_ICO_RADIUS, no misshapen state); the line says what it set."""
    from policy.training.train import TrainConfig, Trainer

    Trainer(TrainConfig(episodes=2, ico_radius=6.0, lidar_max_range=6.5, frames=5,
                        sync=True, start_steps=50, buffer_size=5000, seed=1,
                        progress=False), tmp_path / "run").run()
    proc = _up(tmp_path / "run" / "actor.pt", tmp_path / "s.json")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert ("in the state it was trained on: icosahedron radius 6 m (SKY_ICO_RADIUS; the "
            "LiDAR's range follows), 5 frames a state") in proc.stdout
    policy = json.loads((tmp_path / "s.json").read_text())["counters"]["policy"]
    assert policy["refusals"] == 0 and policy["sent"] >= 15 and policy["bad_actions"] == 0, \
        policy
