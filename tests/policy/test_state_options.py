"""The state-design options end to end (issue 14): an actor trained with ``--encoding
proximity`` flies the stack when perception makes its observations that way
(``skyloop up --encoding proximity``), and holds, counted and said in the summary, when
perception makes them the default way. Real processes on loopback."""

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


@pytest.mark.parametrize("encoding", ["proximity", "distance"])
def test_the_policy_flies_only_observations_made_as_trained(proximity_actor, tmp_path,
                                                           encoding):
    proc = _up(proximity_actor, tmp_path / "s.json", "--encoding", encoding)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    policy = json.loads((tmp_path / "s.json").read_text())["counters"]["policy"]
    if encoding == "proximity":  # as trained: every step answered
        assert policy["refusals"] == 0 and policy["sent"] >= 15, policy
        assert "the policy held the vehicle" not in proc.stdout
    else:  # perception's default encoding: held from the first observation, and said
        assert policy["refusals"] == 1 and policy["sent"] == 0, policy
        assert "the policy held the vehicle 1 time(s)" in proc.stdout
