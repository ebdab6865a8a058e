"""docker/: the compose file parses and names only real ``skyloop`` subcommands.

Without a Docker engine: every node service's command is parsed by the real parser and
run with ``--help`` (a process per subcommand); the graph itself runs through
``skyloop up --router`` in ``tests/stack/test_stack_up.py`` (same nodes, client mode) and, with an
engine, through docker compose in ``tests/stack/test_docker_compose.py``.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from skyloop.cli.stack import bridge_link_config, parse_node, policy_client_config

DOCKER = Path(__file__).resolve().parents[2] / "docker"
NODES = {"sim", "perception", "policy", "bridge", "record"}


def compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


def defaults(arg: str) -> str:
    """``${VAR:-default}`` as compose interpolates it with VAR unset."""
    return re.sub(r"\$\{[A-Z0-9_]+:-([^}]*)\}", r"\1", arg)


def node_commands() -> dict[str, list[str]]:
    services = compose()["services"]
    return {name: [defaults(str(a)) for a in s["command"]] for name, s in services.items()
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
    # the host's UDP 14550 is the ground station's: nothing publishes it; the GCS link's
    # port is published on loopback only, and the Zenoh router not at all
    ports = [p for s in services.values() for p in s.get("ports", [])]
    assert ports == ["127.0.0.1:${SKYLOOP_GCS_LINK_PORT:-18570}:18570/udp"]
    assert "logs" in c["volumes"]
    assert any(v.startswith("logs:") for v in services["record"]["volumes"])
    assert "ARG BASE=python:3.11-slim" in (DOCKER / "Dockerfile").read_text()
    for name in NODES:  # every node has a health check, through skyloop.health
        assert services[name]["healthcheck"]["test"][1:4] == ["python", "-m", "skyloop.health"]


def test_commands_parse():
    from skyloop.cli.stack import COMMANDS
    from skyloop.cli.tools import COMMANDS as TOOLS
    from skyloop.cli.tools import parse_tool

    for name, cmd in node_commands().items():
        assert cmd[0] == name
        if name in TOOLS:  # record
            assert isinstance(parse_tool(cmd), TOOLS[name][0])
        else:
            assert isinstance(parse_node(cmd), COMMANDS[name][0])


def _parsed(name: str, drop: str | None = None):
    cmd = [a for a in node_commands()[name] if a != drop]
    return parse_node(cmd)


def test_mavlink_services_start_with_their_flags(tmp_path):
    """The bridge and the policy build their MAVLink config from the compose flags as
    they do at start-up: bound to 0.0.0.0 with --expose (without it: refused)."""
    bridge = bridge_link_config(_parsed("bridge"))
    assert bridge.gcs.local_host == "0.0.0.0" and bridge.security.expose
    assert bridge.params_file == "/data/state/params-sys1.json"
    services = compose()["services"]
    assert any(v.startswith("state:/data/state") for v in services["bridge"]["volumes"])
    policy = policy_client_config(_parsed("policy"))
    assert policy.listen_host == "0.0.0.0" and policy.security.expose
    for name, build in (("bridge", bridge_link_config), ("policy", policy_client_config)):
        with pytest.raises(ValueError, match="--expose"):
            build(_parsed(name, drop="--expose"))


def test_commands_have_help():
    for cmd in sorted({c[0] for c in node_commands().values()} | {"router", "up"}):
        out = subprocess.run([sys.executable, "-m", "skyloop", cmd, "--help"],
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, (cmd, out.stderr)
        assert "usage:" in out.stdout
