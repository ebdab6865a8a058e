"""The actor-learner through the bus, as real processes on loopback, in lockstep.

Two vehicles (uav1, uav2), each with ``skyloop sim``, ``perception``, ``bridge`` and
``policy --weights-from-bus`` on its own MAVLink ports, and one ``skyloop learner`` for
both. The test process listens on the same bus: it assembles every episode itself (the
learner's assembler) and keeps every actor version published. It checks that the
learner consumed complete episodes of both vehicles, ran updates and published
versions; that both policy nodes swapped to a learner version at an episode start; and
that every step of every episode was flown by the one version its policy node said it
was flying (recomputed from the observations), so no swap happened mid-episode.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch
from loopback import free_port

from bus import keys
from bus.node import Bus
from bus.session import SessionConfig
from perception.observation import FrameStacker
from policy.algorithms.td3 import load_actor
from policy.logs.episode_assembler import TOPICS, EpisodeAssembler
from policy.nodes.learner_node import PUBLISH_LINE, SUMMARY_LINE
from policy.nodes.learner_node import READY_LINE as LEARNER_READY
from policy.nodes.node import READY_LINE as POLICY_READY
from policy.nodes.weights import WEIGHTS_LINE, decode_actor
from policy.training.evaluate import SHIPPED_POLICY
from skyloop.launcher import SIM_READY_LINE

ROOT = Path(__file__).resolve().parents[2]
VEHICLES = ("uav1", "uav2")
# enough episodes that the learner's first versions arrive before the last ones start, even
# on a loaded machine (with 8, a loaded run once saw its first version after the last)
EPISODES, MAX_STEPS = 14, 20


class Proc:
    """A ``python -m skyloop`` child whose output lines are collected by a thread."""

    def __init__(self, name: str, args: list[str], env: dict, stdin: bool = False) -> None:
        self.name, self.lines = name, []
        self.p = subprocess.Popen([sys.executable, "-m", "skyloop", *args], cwd=ROOT, env=env,
                                  stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                  text=True, bufsize=1, start_new_session=True)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.p.stdout:
            self.lines.append(line.rstrip("\n"))

    def has(self, prefix: str) -> bool:
        return any(x.startswith(prefix) for x in self.lines)

    def json_lines(self, prefix: str) -> list[dict]:
        return [json.loads(x[len(prefix):]) for x in list(self.lines) if x.startswith(prefix)]

    def tail(self) -> str:
        return f"--- {self.name} (exit {self.p.poll()}):\n" + "\n".join(self.lines[-25:])


def wait_until(cond, procs: list[Proc], what: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        dead = [p for p in procs if p.p.poll() is not None]
        assert not dead, f"{what}: a node exited\n" + "\n".join(p.tail() for p in dead)
        assert time.monotonic() < deadline, f"{what}: not within {timeout:.0f} s\n" + \
            "\n".join(p.tail() for p in procs)
        time.sleep(0.05)


def stop(procs: list[Proc]) -> None:
    for p in procs:
        if p.p.poll() is None:
            os.killpg(p.p.pid, signal.SIGTERM)
    for p in procs:
        try:
            p.p.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(p.p.pid, signal.SIGKILL)
            p.p.wait(5)


def vehicle_nodes(vehicle: str, index: int, env: dict) -> dict[str, Proc]:
    api, api_local = (free_port(socket.SOCK_DGRAM) for _ in range(2))
    v = ["--vehicle", vehicle]
    return {
        "perception": Proc(f"{vehicle}/perception", ["perception", *v], env),
        "bridge": Proc(f"{vehicle}/bridge", ["bridge", *v, "--no-gcs", "--api-port", str(api),
                                             "--api-local-port", str(api_local)], env),
        "policy": Proc(f"{vehicle}/policy", ["policy", *v, "--lockstep", "--api-port",
                                             str(api), "--weights-from-bus"], env),
        "sim": Proc(f"{vehicle}/sim", ["sim", *v, "--lockstep", "--episodes", str(EPISODES),
                                       "--max-steps", str(MAX_STEPS), "--seed",
                                       str(2000 + 100 * index), "--lockstep-timeout", "20",
                                       "--wait-go"], env, stdin=True),
    }


def flown_actions(observations: dict[int, np.ndarray], T: int, actor) -> np.ndarray:
    """What ``actor`` answers at each step of an episode (as the policy node computes).

    One state per call, shape (1, 105), as the node runs it: a batched matmul may take
    another BLAS kernel and differ in the last float32 bits.
    """
    stacker = FrameStacker(3, 35)
    rows = []
    with torch.no_grad():
        for k in range(T):
            x = np.asarray(stacker.push(observations[k]), np.float32).reshape(1, -1)
            rows.append(actor(torch.as_tensor(x))[0].numpy())
    a = np.stack(rows)
    return np.clip(a.astype(np.float64), -2.0, 2.0).astype(np.float32)


def test_two_workers_and_a_learner_on_loopback(tmp_path):
    torch.set_num_threads(1)
    hub = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "MAVLINK20": "1",
           "SKYLOOP_ZENOH_MODE": "peer", "SKYLOOP_ZENOH_HUB": hub}
    env.pop("SKYLOOP_ZENOH_CONNECT", None)
    # The test's own ears on the bus: every episode and every published version.
    assembler, seen_lock = EpisodeAssembler(), threading.Lock()
    versions: dict[int, object] = {}
    bus = Bus.open(SessionConfig(hub=hub))

    def on_msg(topic, vehicle, msg):
        with seen_lock:
            if topic == keys.ACTOR:
                versions.setdefault(int(msg.version), msg)
            else:
                assembler.add(vehicle, topic, msg, time.monotonic())

    for topic in (*TOPICS, keys.ACTOR):
        bus.subscribe(topic, "*", lambda v, msg, t=topic: on_msg(t, v, msg), with_vehicle=True)
    learner = Proc("learner", ["learner", "--vehicles", *VEHICLES, "--out", str(tmp_path / "l"),
                               "--warmup", "0", "--critic-warmup", "20", "--publish-every", "1",
                               "--updates-per-step", "1", "--buffer-size", "20000",
                               "--no-progress"], env)
    nodes = {v: vehicle_nodes(v, i, env) for i, v in enumerate(VEHICLES)}
    procs = [learner, *(p for n in nodes.values() for p in n.values())]
    try:
        wait_until(lambda: learner.has(LEARNER_READY) and all(
            n["policy"].has(POLICY_READY) and n["sim"].has(SIM_READY_LINE)
            for n in nodes.values()), procs, "learner, policies in OFFBOARD, sims", 150)
        for n in nodes.values():
            n["sim"].p.stdin.write("go\n")
            n["sim"].p.stdin.flush()
        sims = [n["sim"] for n in nodes.values()]
        wait_until(lambda: all(s.p.poll() is not None for s in sims),
                   [p for p in procs if p not in sims], "both sims' episodes", 240)
        assert all(s.p.returncode == 0 for s in sims), "\n".join(s.tail() for s in sims)
        time.sleep(1.0)  # the last messages in flight reach the learner
    finally:
        stop(procs)
        bus.close()
    summary = learner.json_lines(SUMMARY_LINE)
    assert summary, learner.tail()
    s = summary[-1]
    # The learner consumed complete episodes of both vehicles, learned, published.
    assert set(s["by_vehicle"]) == set(VEHICLES), s
    assert s["episodes"] >= 2 * EPISODES - 2 and s["updates"] > 0, s
    assert s["version"] >= 1 and learner.json_lines(PUBLISH_LINE), s
    assert s["skipped"] == {} and s["waiting"] == 0, s

    episodes: dict[str, dict[int, object]] = {}
    for vehicle, index, steps in assembler.poll(time.monotonic() + 60.0):
        episodes.setdefault(vehicle, {})[index] = steps
    shipped = load_actor(SHIPPED_POLICY)
    actors = {0: shipped, **{v: decode_actor(msg, shipped) for v, msg in versions.items()}}
    first: dict[str, int] = {}
    for vehicle, n in nodes.items():
        swaps = n["policy"].json_lines(WEIGHTS_LINE)
        # Both policy nodes swapped to a learner version between episodes.
        assert swaps and all(x["version"] >= 1 for x in swaps), n["policy"].tail()
        assert len(episodes[vehicle]) == EPISODES and not assembler.skipped, assembler.skipped
        flown = {}
        for index, steps in sorted(episodes[vehicle].items()):
            version = max((x for x in swaps if x["episode"] <= index),
                          key=lambda x: x["episode"], default={"version": 0})["version"]
            flown[index] = version
            logged = np.array(steps.actions, np.float32)
            # Every step of the episode is the declared version's answer (to float32
            # rounding: the node and this test may run different BLAS kernels) ...
            np.testing.assert_allclose(logged, flown_actions(steps.observations, steps.steps,
                                                             actors[version]), atol=1e-4)
            # ... and not version 0's once a learner version flies (the swap took effect).
            if version:
                other = flown_actions(steps.observations, steps.steps, actors[0])
                assert np.abs(other - logged).max() > 1e-4
        assert flown[EPISODES - 1] >= 1, flown
        assert list(flown.values()) == sorted(flown.values()), flown  # never backwards
        first[vehicle] = flown[0]
    # Nothing is published before an episode is whole, so the vehicle that finished the
    # first episode flew it with version 0 (a slower one may start on version 1).
    assert min(first.values()) == 0, first
