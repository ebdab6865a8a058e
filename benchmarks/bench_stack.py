"""Stack benchmark: the whole process graph through ``skyloop up`` (loopback peers).

Keys:

- ``stack_lockstep_steps_per_s``: control steps per second of wall time in lockstep,
  shipped policy on the valley (simulator, perception, policy, MAVLink and bridge each a
  process; start-up excluded), as ``skyloop up`` runs it (``--pin auto``: the chain on
  one core, ``skyloop.placement``). Goal: >= 300 (30x real time).
  ``stack_lockstep_recorded_steps_per_s``: the same with the recorder (``--log-dir``, as
  ``make demo``; ``auto`` leaves that unpinned). Peers in the same run:
  ``..._unpinned_...`` (``--pin off``, the code path before pinning) and
  ``..._recorded_pinned_...`` (``--pin chain`` with the recorder). Full mode: 3 repeats,
  interleaved, medians (each repeat's values under ``stack_lockstep_runs``).
- ``stack_lockstep_latency_ms_p50``/``_p99``: per step, scan publish -> the step's
  command back at the simulator (the lockstep round trip through every node).
- ``stack_realtime_latency_ms_p50``/``_p99``: the same in real time (10 Hz, wall
  clock), i.e. scan to setpoint at the vehicle plus one bus hop. Goal: p99 <= 10 ms.
- ``stack_realtime_late_steps``: steps flown on an older command (deadline missed).
- ``stack_lockstep_cpu_ms_per_step``: where the lockstep time goes, node by node: each
  process's CPU time (user + system, all threads, from ``/proc``) from "go" to the sim's
  summary line (start-up, warm-up and shutdown excluded), in ms per control step
  (``skyloop up``'s ``cpu_ms_per_step``); ``stack_lockstep_cpu_ms_per_step_total`` their
  sum. On one core the sum bounds the rate at about 1000 / total steps/s; with two cores
  the nodes overlap only as far as the lockstep chain lets them (one step's hops are
  sequential).

``peers`` holds ``env_steps_per_s``: the in-process env (same policy, same episodes)
measured in the same run, the ceiling the graph is compared with.

Measured 2026-11-22 (full mode, the other core busy with a training run, so the five
processes share about one core): lockstep 170-194 steps/s (goal 300 not met; the nodes
spend about 8 ms of CPU per step together), lockstep p50/p99 2.6-3.0 / 7-8 ms, real
time p50/p99 3.0 / 7.7 ms, env peer 520-580 steps/s. Quick mode takes about 22 s (two
graph start-ups of about 7 s each).

Measured 2026-12-02 (load average 64-71 on the 2 cores: a training grid and other test
runs), two ``run_up("--lockstep", "--episodes", "10")``: 184 and 151 steps/s; CPU ms per
step sim 1.90 / 2.14, perception 0.72 / 0.84, policy 0.67 / 0.70, bridge 0.56 / 0.62,
total 3.85 / 4.29 (less than the 5.4 / 6.6 ms of wall time per step: the nodes waited
for a core). The sim's own wall time per step: publish with the scan 1.1-1.4 ms, flight
and commander 0.7-0.8 ms, waiting for the step's command 3.6-4.4 ms.
"""

from __future__ import annotations

import json
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SEED = 1000


def _free(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_up(*extra: str, timeout: float = 600.0) -> dict:
    """One ``skyloop up`` on free ports; its summary."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "summary.json"
        udp = [_free(socket.SOCK_DGRAM) for _ in range(4)]
        cmd = [sys.executable, "-m", "skyloop", "up", "--hub", f"tcp/127.0.0.1:{_free()}",
               "--api-port", str(udp[0]), "--api-local-port", str(udp[1]),
               "--gcs-port", str(udp[2]), "--gcs-local-port", str(udp[3]),
               "--seed", str(SEED), "--json", str(out), *extra]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        if proc.returncode != 0:
            raise RuntimeError(f"skyloop up failed: {proc.stdout[-2000:]}{proc.stderr[-2000:]}")
        return json.loads(out.read_text())


def env_steps_per_s(episodes: int) -> float:
    """The in-process env with the shipped policy on the same seeds."""
    import torch

    from policy.training.env import UavNavEnv
    from policy.training.evaluate import make_controller
    from policy.training.rollout import run_episode

    torch.set_num_threads(1)
    controller, env = make_controller(None), UavNavEnv(scenario="valley")
    run_episode(env, controller, SEED)  # warm up
    t0, steps = time.perf_counter(), 0
    for i in range(episodes):
        steps += run_episode(env, controller, SEED + i).steps
    return steps / (time.perf_counter() - t0)


def lockstep_runs(episodes: int, repeats: int) -> dict[str, list[dict]]:
    """Summaries of lockstep runs, pinned and not, with and without the recorder,
    interleaved ``repeats`` times."""
    runs: dict[str, list[dict]] = {}
    settings = {"": (False, "auto"), "unpinned_": (False, "off"),
                "recorded_": (True, "auto"), "recorded_pinned_": (True, "chain")}
    for _ in range(repeats):
        for key, (rec, pin) in settings.items():
            with tempfile.TemporaryDirectory() as tmp:
                log = ["--log-dir", tmp] if rec else []
                runs.setdefault(key, []).append(
                    run_up("--lockstep", "--episodes", str(episodes), "--pin", pin, *log))
    return runs


def run(quick: bool) -> dict:
    runs = lockstep_runs(1 if quick else 10, 1 if quick else 3)
    rows = {k: [round(r["steps_per_s"], 1) for r in v] for k, v in runs.items()}
    lock = runs[""][0]  # latency and CPU: the first default run
    rt = run_up("--realtime", "--episodes", "1", "--max-steps", "20") if quick else \
        run_up("--realtime", "--episodes", "3")
    cpu = lock.get("cpu_ms_per_step")  # absent where there is no /proc
    med = {k: statistics.median(v) for k, v in rows.items()}
    return {
        "stack_lockstep_steps_per_s": med[""],
        "stack_lockstep_recorded_steps_per_s": med["recorded_"],
        "stack_lockstep_latency_ms_p50": lock.get("latency_ms_p50"),
        "stack_lockstep_latency_ms_p99": lock.get("latency_ms_p99"),
        "stack_realtime_latency_ms_p50": rt.get("latency_ms_p50"),
        "stack_realtime_latency_ms_p99": rt.get("latency_ms_p99"),
        "stack_realtime_late_steps": rt.get("late_steps"),
        "stack_lockstep_cpu_ms_per_step": cpu,
        "stack_lockstep_cpu_ms_per_step_total": round(sum(cpu.values()), 3) if cpu else None,
        "stack_lockstep_runs": {f"stack_lockstep_{k}steps_per_s": v for k, v in rows.items()},
        "peers": {"inprocess_env_shipped_policy_steps_per_s": env_steps_per_s(1 if quick else 10),
                  "stack_lockstep_unpinned_steps_per_s": med["unpinned_"],
                  "stack_lockstep_recorded_pinned_steps_per_s": med["recorded_pinned_"]},
    }


if __name__ == "__main__":
    print(json.dumps(run("--quick" in sys.argv), indent=2))
