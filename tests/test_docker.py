"""docker/: the compose file parses and names only real ``skyloop`` subcommands.

No Docker engine here: every node service's command is parsed by the real parser and
run with ``--help`` (a process per subcommand); the graph itself runs through
``skyloop up --router`` in ``tests/test_stack_up.py`` (same nodes, client mode).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import yaml

from skyloop.cli import build_parser

DOCKER = Path(__file__).resolve().parent.parent / "docker"
NODES = {"sim", "perception", "policy", "bridge", "record"}


def compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


def node_commands() -> dict[str, list[str]]:
    services = compose()["services"]
    return {name: [str(a) for a in s["command"]] for name, s in services.items()
            if name != "router"}


def test_compose_shape():
    c = compose()
    services = c["services"]
    assert set(services) == NODES | {"router"}
    assert services["router"]["image"].startswith("eclipse/zenoh")
    for name in NODES:
        env = services[name]["environment"]
        assert env["SKYLOOP_ZENOH_MODE"] == "client"
        assert env["SKYLOOP_ZENOH_CONNECT"] == "tcp/router:7447"
    assert "14550:14550/udp" in services["bridge"]["ports"]
    assert "logs" in c["volumes"]
    assert any(v.startswith("logs:") for v in services["record"]["volumes"])
    assert "FROM python:3.11" in (DOCKER / "Dockerfile").read_text()


def test_commands_parse():
    parser = build_parser()
    for name, cmd in node_commands().items():
        assert cmd[0] == name
        if name == "record":
            from bus.record import build_parser as record_parser

            record_parser().parse_args(cmd[1:])
        else:
            args = parser.parse_args([a.replace("${SKYLOOP_GCS_HOST:-host.docker.internal}",
                                                "host.docker.internal") for a in cmd])
            assert args.command == name


def test_commands_have_help():
    for cmd in sorted({c[0] for c in node_commands().values()} | {"router", "up"}):
        out = subprocess.run([sys.executable, "-m", "skyloop", cmd, "--help"],
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, (cmd, out.stderr)
        assert "usage:" in out.stdout
