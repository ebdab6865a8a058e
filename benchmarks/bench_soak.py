"""Soak benchmark: the stack in real time for N minutes (``skyloop bench --only soak
--minutes N``; not part of the default run).

``skyloop up --realtime`` with the shipped policy on the valley flies seeded episodes
back to back, measured for N minutes from the first control step (the first ``clock``
message on the bus). The benchmark watches from outside, as a ground station would:

- RSS of every node, the recorder included (``/proc/<pid>/status`` VmRSS), once warmed
  up (a minute in, or half the first window) and at the end; goal: growth < 5 % per
  node.
- Per window (10 minutes, or a third of a shorter run): the loop latency seen on the
  bus, from a step's ``clock`` message to its ``cmd_vel`` (the bridge's setpoint for
  that step: perception, policy, MAVLink and bridge in between), p50/p90/p99/max; steps
  whose setpoint came more than one control period late (``late``) or never
  (``missing``).
- The launcher's summary at the end (SIGINT after N minutes): episodes, outcomes, and
  what each node's bounded queues dropped (``soak_dropped``: node -> count; the nodes'
  counters lines, ``skyloop.launcher.COUNTERS_LINE``).

Keys: ``soak_minutes``, ``soak_steps``, ``soak_rss_growth_pct_max``,
``soak_rss_mb`` (node -> [warm, end]), ``soak_windows`` (list of per-window dicts),
``soak_dropped``.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from benchmarks.bench_stack import _free
from skyloop import launcher

PERIOD_NS = 100_000_000
WINDOW_S = 600.0


def rss_mb(pid: int) -> float | None:
    try:
        text = open(f"/proc/{pid}/status").read()
    except OSError:
        return None
    m = re.search(r"VmRSS:\s+(\d+) kB", text)
    return int(m.group(1)) / 1024 if m else None


class LoopWatch:
    """Arrival times of each step's ``clock`` and ``cmd_vel`` on the bench's own session."""

    def __init__(self, hub: str) -> None:
        from bus import keys
        from bus import messages as m
        from bus.node import Bus
        from bus.session import SessionConfig

        self.lock = threading.Lock()
        self.clock: dict[int, float] = {}  # stamp ns -> arrival (monotonic s)
        self.cmd: dict[int, float] = {}
        self.first = threading.Event()  # a step's clock came: the episodes have begun
        self.bus = Bus.open(SessionConfig(hub=hub))
        self.bus.subscribe(keys.CLOCK, "uav1", lambda msg: self._put(
            self.clock, m.nanoseconds(msg.sim_time), self.first))
        self.bus.subscribe(keys.CMD_VEL, "uav1", lambda msg: self._put(
            self.cmd, m.nanoseconds(msg.header.stamp)))

    def _put(self, table: dict[int, float], stamp: int,
             seen: threading.Event | None = None) -> None:
        with self.lock:
            table.setdefault(stamp, time.monotonic())
        if seen is not None:
            seen.set()

    def window(self, t0: float, t1: float) -> dict:
        """Steps whose clock arrived in [t0, t1), settled (read after t1 + 1 s)."""
        with self.lock:
            steps = [(s, t) for s, t in self.clock.items() if t0 <= t < t1]
            lat = [(self.cmd[s] - t) * 1e3 for s, t in steps if s in self.cmd]
            for s, _ in steps:  # forget what is counted
                self.clock.pop(s, None)
                self.cmd.pop(s, None)
        a = np.array(lat) if lat else np.zeros(1)
        p50, p90, p99 = (float(x) for x in np.percentile(a, [50, 90, 99]))
        return {"steps": len(steps), "latency_ms_p50": p50, "latency_ms_p90": p90,
                "latency_ms_p99": p99, "latency_ms_max": float(a.max()),
                "late": int(np.sum(a > PERIOD_NS / 1e6)), "missing": len(steps) - len(lat)}

    def close(self) -> None:
        self.bus.close()


def run(quick: bool, minutes: float | None = None) -> dict:
    minutes = minutes if minutes is not None else (2.0 if quick else 60.0)
    total_s = minutes * 60.0
    window_s = min(WINDOW_S, total_s / 3)
    hub = f"tcp/127.0.0.1:{_free()}"
    udp = [_free(socket.SOCK_DGRAM) for _ in range(4)]
    logs = tempfile.TemporaryDirectory()  # the recorder runs too (its memory counts)
    cmd = [sys.executable, "-m", "skyloop", "up", "--realtime", "--episodes", "1000000",
           "--log-dir", logs.name, "--json", os.path.join(logs.name, "summary.json"),
           "--hub", hub, "--api-port", str(udp[0]), "--api-local-port", str(udp[1]),
           "--gcs-port", str(udp[2]), "--gcs-local-port", str(udp[3])]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    watch = LoopWatch(hub)  # after the fork: never fork with a session open
    pids: dict[str, int] = {}
    lines: list[str] = []

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            if (node := launcher.started(line)) is not None:
                pids[node[0]] = node[1]

    threading.Thread(target=read, daemon=True).start()
    try:
        deadline = time.monotonic() + 180.0
        while not watch.first.wait(0.2):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the stack did not fly (it exited, or 180 s passed): "
                                   + "".join(lines[-20:]))
        t_start = time.monotonic()
        warm: dict[str, float | None] = {}
        windows = []
        t = t_start
        while t < t_start + total_s - 1e-6:
            end = min(t + window_s, t_start + total_s)
            while time.monotonic() < end:
                if proc.poll() is not None:
                    raise RuntimeError("the stack stopped: " + "".join(lines[-20:]))
                if not warm and time.monotonic() > t_start + min(60.0, window_s / 2):
                    warm = {name: rss_mb(pid) for name, pid in pids.items()}
                time.sleep(1.0)
            time.sleep(1.0)  # let the last setpoints of the window arrive
            w = watch.window(t, end)
            w["minute"] = round((end - t_start) / 60.0, 1)
            windows.append(w)
            print(f"    soak {w['minute']:.1f}/{minutes:g} min: {w['steps']} steps, latency "
                  f"p50 {w['latency_ms_p50']:.1f} p90 {w['latency_ms_p90']:.1f} p99 "
                  f"{w['latency_ms_p99']:.1f} ms, late {w['late']}, missing {w['missing']}",
                  flush=True)
            t = end
        final = {name: rss_mb(pid) for name, pid in pids.items()}
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30.0)
        except subprocess.TimeoutExpired:
            proc.kill()
        watch.close()
        try:
            counters = json.load(open(os.path.join(logs.name, "summary.json")))["counters"]
        except (OSError, ValueError, KeyError):  # the launcher died before its summary
            counters = {}
        logs.cleanup()
    summary = next((x for x in lines if x.startswith("summary: ")), "").strip()
    rss = {name: [round(warm[name], 1), round(final[name], 1)] for name in pids
           if warm.get(name) and final.get(name)}
    growth = {name: 100.0 * (b - a) / a for name, (a, b) in rss.items()}
    return {"soak_minutes": minutes, "soak_steps": sum(w["steps"] for w in windows),
            "soak_rss_mb": rss, "soak_rss_growth_pct_max": max(growth.values(), default=0.0),
            "soak_windows": windows, "soak_summary": summary,
            "soak_dropped": {name: c.get("dropped", 0) for name, c in counters.items()},
            "peers": {}}


if __name__ == "__main__":
    mins = float(os.environ.get("SOAK_MINUTES", "2"))
    print(json.dumps(run(False, mins), indent=2))
