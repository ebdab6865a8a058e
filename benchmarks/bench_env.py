"""Env benchmark: full ``skyloop/UavNav-v0`` steps/s (truncated LiDAR) vs PyFlyt's QuadX.

``env_steps_per_s`` is one control step end to end (JSBSim 50 physics steps, autopilot,
estimator, collision check, VLP-16 scan truncated at 4.5 m, icosahedron, reward) under
the scripted controller, median of several repeats. The peer runs in ``.venv-peers``
(see ``peer_pyflyt.py``); when that venv is missing the peer is reported as skipped.

``render_fps`` is ``env.render()`` alone (``render_mode="rgb_array"``, the fast 640x480
renderer of ``sitl.render.frames``) on frames of a scripted episode, after the first
frame and a few warm-up frames, median of several repeats; ``render_first_frame_ms`` is
the first frame of a fresh env (the per-world map precompute and one frame), median of
a few fresh envs.

``world_build_ms`` is what a new world drawn for an episode costs (``family:`` and
``mix:`` scenarios, ``sitl.world.families``): the terrain, obstacles, collision structures,
free-space grid and the LiDAR's Embree scene (``EpisodeSim.use_world``), median over
fresh worlds of each family, per family under ``world_build_ms_by_family``. Compare with
an episode: ``env_steps_per_s`` and 100-300 steps.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import time
from pathlib import Path

from policy.algorithms.scripted import StraightLineController
from policy.training.env import UavNavEnv

PEER_PYTHON = Path(__file__).resolve().parent.parent / ".venv-peers" / "bin" / "python"


def measure_env(steps: int, repeats: int, scenario: str = "valley") -> float:
    env = UavNavEnv(scenario=scenario)
    controller = StraightLineController()
    state, _ = env.reset(seed=0)
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            state, _, term, trunc, _ = env.step(controller(state))
            if term or trunc:
                state, _ = env.reset()
        rates.append(steps / (time.perf_counter() - t0))
    return statistics.median(rates)


def measure_render(frames: int, repeats: int, scenario: str = "valley") -> dict:
    controller = StraightLineController()
    first = []
    for k in range(max(repeats // 2, 2)):
        env = UavNavEnv(scenario=scenario, render_mode="rgb_array")
        env.reset(seed=k)
        t0 = time.perf_counter()
        env.render()
        first.append(time.perf_counter() - t0)
    state, _ = env.reset(seed=0)
    for _ in range(5):  # warm-up frames
        env.render()
    rates = []
    for _ in range(repeats):
        spent = 0.0
        for _ in range(frames):
            state, _, term, trunc, _ = env.step(controller(state))
            if term or trunc:
                state, _ = env.reset()
            t0 = time.perf_counter()
            frame = env.render()
            spent += time.perf_counter() - t0
        rates.append(frames / spent)
    assert frame.shape == (480, 640, 3)
    return {"render_fps": statistics.median(rates),
            "render_first_frame_ms": 1e3 * statistics.median(first)}


def measure_pyflyt(steps: int, repeats: int) -> dict:
    if not PEER_PYTHON.exists():
        return {"pyflyt_quadx_waypoints_steps_per_s": None,
                "pyflyt_note": "skipped: .venv-peers missing (make bench creates it)"}
    script = Path(__file__).with_name("peer_pyflyt.py")
    out = subprocess.run([str(PEER_PYTHON), str(script), str(steps), str(repeats)],
                         capture_output=True, text=True, timeout=600, check=False)
    if out.returncode != 0:
        return {"pyflyt_quadx_waypoints_steps_per_s": None,
                "pyflyt_note": f"failed: {out.stderr.strip().splitlines()[-1:]}"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def measure_world_build(worlds: int) -> dict:
    """Median ms to build a fresh world of each family into an episode core."""
    from sitl.episode import EpisodeSim
    from sitl.world.families import VALIDATION_SEED0

    sim = EpisodeSim()
    sim.use_world("forest#1")  # warm-up: numba kernels, Embree
    by_family = {}
    for family in ("valley", "forest", "city", "dynamic"):
        times = []
        for i in range(worlds):
            t0 = time.perf_counter()
            sim.use_world(f"{family}#{VALIDATION_SEED0 + 10_000 + i}")  # not built before
            times.append((time.perf_counter() - t0) * 1000)
        by_family[family] = statistics.median(times)
    return {"world_build_ms": statistics.median(by_family.values()),
            "world_build_ms_by_family": by_family}


def run(quick: bool) -> dict:
    steps, repeats = (300, 3) if quick else (1500, 5)
    result = {"env_steps_per_s": measure_env(steps, repeats)}
    result.update(measure_world_build(3 if quick else 7))
    result.update(measure_render(100 if quick else 300, repeats))
    result["peers"] = measure_pyflyt(steps, repeats)
    return result
