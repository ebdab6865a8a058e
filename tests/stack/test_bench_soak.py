"""A smoke run of the soak benchmark (issue 13, "Time and load"): ``skyloop bench --only
soak --minutes 0.2`` -- the real-time stack with the shipped policy and the recorder, 12
s from its first control step -- gives a result of the documented shape whose numbers
are sane. Structure only: no timing goal is asserted (the hour-long run in
benchmarks/results/ is where the goals are judged)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
NODES = {"sim", "perception", "policy", "bridge", "record"}  # skyloop up --log-dir


@pytest.mark.slow
def test_a_short_soak_reports_every_node(tmp_path):
    out = tmp_path / "soak.json"
    proc = subprocess.run([sys.executable, "-m", "skyloop", "bench", "--only", "soak",
                           "--minutes", "0.2", "--json", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    r = json.loads(out.read_text())  # flat: results beside "machine", "command", ...
    assert r["soak_minutes"] == 0.2
    # RSS of every node, warmed up and at the end
    assert set(r["soak_rss_mb"]) == NODES, r["soak_rss_mb"]
    assert all(len(v) == 2 and v[0] > 0 and v[1] > 0 for v in r["soak_rss_mb"].values()), \
        r["soak_rss_mb"]
    assert isinstance(r["soak_rss_growth_pct_max"], float)
    # what each node's bounded queues dropped (its counters line at exit)
    assert set(r["soak_dropped"]) == NODES, r["soak_dropped"]
    assert all(isinstance(v, int) and v >= 0 for v in r["soak_dropped"].values())
    # windows: a third of the run each, steps flown, latency percentiles in order
    windows = r["soak_windows"]
    assert len(windows) == 3, windows
    assert all(w["steps"] > 0 for w in windows), windows
    assert r["soak_steps"] == sum(w["steps"] for w in windows) > 0
    for w in windows:
        assert 0 <= w["latency_ms_p50"] <= w["latency_ms_p90"] <= w["latency_ms_p99"] \
            <= w["latency_ms_max"], w
        assert 0 <= w["late"] <= w["steps"] and 0 <= w["missing"] <= w["steps"], w
    assert [w["minute"] for w in windows] == sorted(w["minute"] for w in windows)
    assert r["soak_summary"].startswith("summary: "), r["soak_summary"]  # the launcher's
