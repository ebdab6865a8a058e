"""The ``skyloop`` command end to end, as a user runs it."""

from __future__ import annotations

import json
import socket
import subprocess
import sys

import pytest


def skyloop(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "skyloop", *args], capture_output=True,
                          text=True, timeout=timeout)


def test_one_version_for_the_command_and_the_vehicle():
    from importlib.metadata import version

    from mavlink_bridge.gcs.autopilot_version import autopilot_version

    out = skyloop("--version")
    assert out.returncode == 0 and out.stdout.strip() == f"skyloop {version('skyloop')}"
    sw = autopilot_version(1).flight_sw_version  # PX4 packing: major.minor.patch.type
    packed = ".".join(str(sw >> shift & 0xFF) for shift in (24, 16, 8))
    assert packed == ".".join(version("skyloop").split(".")[:3])


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


def test_mavlink_nodes_refuse_to_expose_without_the_flag():
    for cmd in (["bridge", "--bind", "0.0.0.0"], ["policy", "--api-host", "0.0.0.0"]):
        out = skyloop(*cmd, timeout=60)
        assert out.returncode != 0
        assert "--expose" in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_security_flags_reach_bridge_and_policy(tmp_path):
    """``skyloop up`` hands the same key and allow-list to the bridge and the policy, and
    each builds a signing endpoint from them (a bad key file is a clear error)."""
    from skyloop.cli.stack import bridge_link_config, parse_node, policy_client_config
    from skyloop.launcher import _node_args

    key = tmp_path / "key"
    key.write_text("correct horse battery staple\n")
    up = parse_node(["up", "--signing-key-file", str(key), "--allow-sysid", "255",
                     "--expose", "--param", "COM_OF_LOSS_T=0.5"])
    nodes = _node_args(up, {"api": 1, "api_local": 2, "gcs": 3, "gcs_local": 4})
    built = {"bridge": bridge_link_config, "policy": policy_client_config}
    for name, build in built.items():
        sec = build(parse_node(nodes[name])).security
        assert sec.secret_key is not None and len(sec.secret_key) == 32
        assert sec.allow_sysids == frozenset({255})
    assert "--expose" in nodes["bridge"] and "--expose" not in nodes["policy"]
    assert nodes["bridge"].count("--param") == nodes["sim"].count("--param") == 1
    key.write_text("")
    out = skyloop("bridge", "--signing-key-file", str(key), timeout=60)
    assert out.returncode != 0 and "Traceback" not in out.stderr, out.stderr


def test_bad_counts_are_refused_before_anything_starts():
    for args, flag in ((("up", "--episodes", "-1"), "--episodes"),
                       (("eval", "--episodes", "-1"), "--episodes"),
                       (("train", "--episodes", "0", "--out", "unused"), "--episodes"),
                       (("train", "--envs", "x", "--out", "unused"), "--envs"),
                       (("sim", "--max-steps", "0"), "--max-steps")):
        out = skyloop(*args, timeout=60)
        assert out.returncode == 2, args
        assert f"argument {flag}:" in out.stderr and "Traceback" not in out.stderr, args


@pytest.mark.timing
def test_policy_stops_on_sigterm_while_waiting_for_the_vehicle():
    """Start-up (waiting 30 s for a heartbeat that never comes) ends within 2 s of
    SIGTERM, cleanly."""
    import os
    import signal
    import time

    from loopback import free_port

    port = free_port(socket.SOCK_DGRAM)
    proc = subprocess.Popen([sys.executable, "-m", "skyloop", "policy", "--policy",
                             "scripted", "--api-port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        assert proc.stderr is not None
        for line in proc.stderr:
            if "waiting up to" in line and "heartbeat" in line:
                break
        proc.send_signal(signal.SIGTERM)
        t0 = time.monotonic()
        err = proc.communicate(timeout=10)[1]
        assert time.monotonic() - t0 < 5.0  # measured 0.65 s; slack for a loaded machine
        assert proc.returncode == 143 and "Traceback" not in err, err
    finally:
        if proc.poll() is None:
            proc.kill()


def test_a_taken_mavlink_port_names_the_port_and_the_flag():
    from loopback import free_port

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        port = free_port(socket.SOCK_DGRAM)
        taken.bind(("127.0.0.1", port))
        for args, flag in ((("bridge", "--no-gcs", "--api-local-port", str(port)),
                            "--api-local-port"),
                           (("bridge", "--gcs-local-port", str(port)), "--gcs-local-port"),
                           (("policy", "--policy", "scripted", "--api-port", str(port)),
                            "--api-port")):
            out = skyloop(*args, timeout=60)
            assert out.returncode == 2, out.stderr
            assert f"127.0.0.1:{port}: Address already in use" in out.stderr, out.stderr
            assert flag in out.stderr and "Traceback" not in out.stderr
