"""The ``skyloop`` command end to end, as a user runs it."""

from __future__ import annotations

import json
import subprocess
import sys


def skyloop(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "skyloop", *args], capture_output=True,
                          text=True, timeout=timeout)


def test_help_lists_the_subcommands():
    out = skyloop("--help")
    assert out.returncode == 0
    for name in ("demo", "render", "bench", "train", "eval", "plot"):
        assert name in out.stdout


def test_render_writes_a_png(tmp_path):
    png = tmp_path / "valley.png"
    out = skyloop("render", "--scenario", "forest", "--seed", "2", "--out", str(png))
    assert out.returncode == 0, out.stderr[-2000:]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_demo_flies_the_shipped_policy_and_compares_with_scripted(tmp_path):
    js = tmp_path / "demo.json"
    out = skyloop("demo", "--episodes", "2", "--out-dir", str(tmp_path), "--json", str(js))
    assert out.returncode == 0, out.stderr[-2000:]
    assert "shipped" in out.stdout and "scripted straight-line controller" in out.stdout
    assert "summary: success" in out.stdout
    data = json.loads(js.read_text())
    assert data["episodes"] == 2 and (tmp_path / "demo_valley.png").exists()


def test_unknown_scenario_is_a_clear_error(tmp_path):
    out = skyloop("render", "--scenario", "atlantis", "--out", str(tmp_path / "x.png"))
    assert out.returncode == 2
    assert "atlantis" in out.stderr and "valley" in out.stderr and "Traceback" not in out.stderr


def test_bench_quick_writes_json(tmp_path):
    js = tmp_path / "bench.json"
    out = skyloop("bench", "--quick", "--only", "perception", "--json", str(js))
    assert out.returncode == 0, out.stderr[-2000:]
    data = json.loads(js.read_text())
    assert data["perception_ms_28800"] > 0 and "machine" in data and "peers" in data
