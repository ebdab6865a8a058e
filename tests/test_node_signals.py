"""Every node exits soon after SIGTERM or SIGINT once up, cleanly (no traceback), as a
supervisor (skyloop up, docker stop, systemd) expects: measured 0.1-0.7 s here (the goal
is 2 s; the test allows 5 for a loaded machine). Real programs on loopback."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
from loopback import free_port, sigint_default

NODES = {  # node -> (arguments, a line it prints once up)
    "sim": (["sim", "--wait-go"], "SKYLOOP-SIM-READY"),
    "perception": (["perception"], "perception up"),
    "bridge": (["bridge", "--no-gcs"], "bridge up"),
    "record": (["record"], "recording"),
    "policy": (["policy", "--policy", "scripted"], "heartbeat"),  # waiting for the vehicle
}


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["sigterm", "sigint"])
@pytest.mark.parametrize("node", sorted(NODES))
def test_a_node_stops_within_2_s_of_a_signal(node, sig, tmp_path):
    args, up_line = NODES[node]
    udp = [str(free_port(socket.SOCK_DGRAM)) for _ in range(2)]
    extra = {"bridge": ["--api-local-port", udp[0], "--api-port", udp[1]],
             "policy": ["--api-port", udp[0]], "record": ["--out", str(tmp_path)]}
    env = dict(os.environ, SKYLOOP_ZENOH_HUB=f"tcp/127.0.0.1:{free_port()}",
               PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "skyloop", *args, *extra.get(node, [])],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True, preexec_fn=sigint_default,
                            stdin=subprocess.PIPE)  # the sim's --wait-go waits on it
    lines: list[str] = []
    up = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            if up_line in line:
                up.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert up.wait(120), "".join(lines)[-2000:]
        proc.send_signal(sig)
        t0 = time.monotonic()
        proc.wait(timeout=10)
        assert time.monotonic() - t0 < 5.0
        reader.join(5)
        out = "".join(lines)
        assert "Traceback" not in out, out[-2000:]
        # a node with a stop event exits 0; one interrupted mid-call 128 + the signal
        assert proc.returncode in (0, 128 + sig), (proc.returncode, out[-500:])
    finally:
        if proc.poll() is None:
            proc.kill()
