"""A bus that lets no one in (issue 13 §4), on loopback with real Zenoh sessions: a router
on a ``tls/`` endpoint with the configuration ``skyloop certs`` writes (mutual TLS,
access control by certificate common name), nodes as clients with theirs."""

from __future__ import annotations

import shutil
import socket
import threading
import time

import pytest
from loopback import free_port, wait_for

from bus import keys
from bus import messages as m
from bus.certs import make_certs
from bus.node import Bus
from bus.session import SessionConfig, run_router

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="no openssl command")


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    return make_certs(tmp_path_factory.mktemp("certs"), ("router", "sim", "perception",
                                                         "bridge"))


@pytest.fixture
def router(certs):
    endpoint = f"tls/localhost:{free_port()}"
    stop = threading.Event()
    thread = threading.Thread(target=run_router, args=(endpoint, stop, SessionConfig(
        mode="router", config_file=str(certs / "router.json5"))), daemon=True)
    thread.start()
    time.sleep(1.0)  # listening
    yield endpoint
    stop.set()
    thread.join(5.0)


def client(endpoint: str, config_file: str | None) -> Bus:
    return Bus.open(SessionConfig(mode="client", connect=(endpoint,), config_file=config_file,
                                  connect_timeout_s=3.0))


def test_only_the_bridge_commands_the_vehicle(certs, router):
    sim, perception, bridge = (client(router, str(certs / f"{n}.json5"))
                               for n in ("sim", "perception", "bridge"))
    got: list[str] = []
    try:
        sim.subscribe(keys.CMD_VEL, "uav1", lambda msg: got.append(msg.header.frame_id))
        sim.subscribe(keys.OBSERVATION, "uav1", lambda msg: got.append("observation"))
        time.sleep(1.0)  # declarations reach the router
        for bus, frame in ((perception, "world"), (bridge, "base_link")):
            bus.publisher(keys.CMD_VEL, "uav1").put(
                m.velocity_setpoint((1, 0, 0), 0.0, 0.1, body=frame == "base_link"))
        perception.publisher(keys.OBSERVATION, "uav1").put(m.observation([0.0] * 35, 0.1))
        wait_for(lambda: len(got) >= 2, 5.0, "the bridge's setpoint and the observation")
        time.sleep(0.5)
        # perception's setpoint was dropped at the router; its observation went through
        assert sorted(got) == ["base_link", "observation"], got
    finally:
        for b in (sim, perception, bridge):
            b.close()


def test_no_certificate_or_another_ca_cannot_connect(certs, router, tmp_path):
    other = make_certs(tmp_path / "other", ("sim",))  # a CA the router does not trust
    for config in (None, str(other / "sim.json5")):
        with pytest.raises(Exception, match="connect|Timeout|timeout"):
            client(router, config)
    ok = client(router, str(certs / "sim.json5"))  # and the right one can
    ok.close()


def test_a_bad_config_file_is_named(tmp_path):
    bad = tmp_path / "bad.json5"
    bad.write_text("{ this is not json5")
    for path, why in ((str(bad), "bad.json5"), (str(tmp_path / "none.json5"), "no such file")):
        with pytest.raises(ValueError, match=why):
            SessionConfig(config_file=path).zenoh_config()


def test_the_stack_flies_on_a_secured_bus(certs, tmp_path):
    """``skyloop up --router --zenoh-config-dir DIR``: the router on a tls endpoint, every
    node with its own certificate, the bridge's setpoints allowed: episodes fly."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    full = make_certs(tmp_path / "certs")  # every node of a stack, the launcher too
    root = Path(__file__).resolve().parent.parent
    udp = [str(free_port(socket.SOCK_DGRAM)) for _ in range(4)]
    cmd = [sys.executable, "-m", "skyloop", "up", "--router", "--zenoh-config-dir", str(full),
           "--episodes", "1", "--policy", "scripted", "--json", str(tmp_path / "s.json"),
           "--api-port", udp[0], "--api-local-port", udp[1], "--gcs-port", udp[2],
           "--gcs-local-port", udp[3]]
    proc = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert json.loads((tmp_path / "s.json").read_text())["episodes"] == 1
    no_router = subprocess.run([sys.executable, "-m", "skyloop", "up", "--zenoh-config-dir",
                                str(full)], cwd=root, capture_output=True, text=True, timeout=60)
    assert no_router.returncode == 2 and "needs --router" in no_router.stderr
    partial = subprocess.run([sys.executable, "-m", "skyloop", "up", "--router",
                              "--zenoh-config-dir", str(certs)], cwd=root, capture_output=True,
                             text=True, timeout=60)  # no launcher/policy/... configs there
    assert partial.returncode == 2 and "launcher.json5" in partial.stderr, partial.stderr
