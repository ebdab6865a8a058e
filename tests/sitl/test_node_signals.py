"""Every node exits within 2 s of SIGTERM or SIGINT at any moment of its life, cleanly
(issue 13), as a supervisor (skyloop up, docker stop, systemd) expects. Real programs on
loopback; the moments and signals are drawn from a seeded generator.

* Alone (each node but the viewer and the learner, ~4 s to start each): once up and
  waiting (the policy for the vehicle's heartbeat, the sim for "go", the others for
  data), a random moment later; then again at a random moment of its start-up (imports,
  parsing, opening the bus: between its start and the time the first run took to come
  up). One signal SIGTERM, the other SIGINT.
* Mid-episode (every node of one ``skyloop up --router --log-dir --viz save:...``,
  flying; the viewer only here: it starts as slowly as the policy, and costs nothing
  more in a graph that starts at once): each gets a random one of the two signals at
  one random moment of an episode. The launcher is stopped (SIGSTOP) meanwhile, so that
  each node's own stop is measured, not the launcher's SIGTERM after the first death;
  its readers then show what the nodes printed (``--verbose``).

* Orphaned at birth: a launcher that dies between a child's fork and its parent-death
  ``prctl`` sends that child no signal; the child exits at once instead of running
  (``launcher._pdeathsig``'s check of its parent).

Each time: the process exits within 2 s of the signal, as seen from here; exits 0 (a node
whose stop event ended it) or 128 + the signal (``skyloop.signals``: the signal ended
it mid-call, or during start-up); prints no traceback; and leaves no process of its
session behind. Nodes are started as ``skyloop up`` starts them, the stop signals held
until skyloop's first line (``skyloop.signals.block_until_started``).
"""

from __future__ import annotations

import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from loopback import (
    alive,
    exit_status,
    free_port,
    session_members,
    sigint_default,
    started_blocked,
    up_args,
)

from skyloop import launcher

pytestmark = pytest.mark.timing  # wall-clock deadlines: run alone (conftest, Makefile)
SEED = int(os.environ.get("SKYLOOP_SIGNAL_SEED", "13"))  # another seed: other moments
LIMIT_S = 2.0  # issue 13: from the signal to the exit
SIGNALS = (signal.SIGTERM, signal.SIGINT)
ROOT = Path(__file__).resolve().parents[2]
NODES = {  # node -> (arguments, the line it prints once up and waiting)
    "sim": (["sim", "--wait-go"], "SKYLOOP-SIM-READY"),  # its ground phase, until "go"
    "perception": (["perception"], "perception up"),
    "bridge": (["bridge", "--no-gcs"], "bridge up"),  # no vehicle yet: no heartbeat
    "record": (["record"], "recording"),
    "policy": (["policy", "--policy", "scripted"], "heartbeat"),  # waiting for one
    "router": (["router"], "listening on"),
}


class Node:
    """A node program started now, and what it prints (read by a thread)."""

    def __init__(self, node: str, tmp: Path) -> None:
        args, self.up_line = NODES[node]
        udp = [str(free_port(socket.SOCK_DGRAM)) for _ in range(2)]
        hub = f"tcp/127.0.0.1:{free_port()}"
        extra = {"bridge": ["--api-local-port", udp[0], "--api-port", udp[1]],
                 "policy": ["--api-port", udp[0]], "record": ["--out", str(tmp)],
                 "router": ["--listen", hub]}.get(node, [])
        env = dict(os.environ, SKYLOOP_ZENOH_HUB=hub, PYTHONUNBUFFERED="1")
        self.t0 = time.monotonic()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "skyloop", *args, *extra], cwd=ROOT, env=env,
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, start_new_session=True, preexec_fn=started_blocked)
        self.lines: list[str] = []
        self.up = threading.Event()
        self.up_s = float("nan")  # from the start to the up line
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)
            if self.up_line in line and not self.up.is_set():
                self.up_s = time.monotonic() - self.t0
                self.up.set()

    def stop(self, sig: signal.Signals, moment: str) -> float:
        """Send ``sig``, wait for the exit, check it (see the module docstring); the
        seconds from the signal to the exit."""
        pid = self.proc.pid
        t = time.monotonic()
        os.kill(pid, sig)
        try:
            self.proc.wait(timeout=LIMIT_S + 10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        took = time.monotonic() - t
        self.reader.join(5)
        out = "".join(self.lines)
        what = f"{sig.name} {moment} ({t - self.t0:.2f} s after the start)"
        assert took < LIMIT_S, f"{what}: exited {took:.2f} s after it\n{out[-3000:]}"
        assert self.proc.returncode in (0, 128 + sig), (what, self.proc.returncode, out[-3000:])
        assert "Traceback" not in out, f"{what}\n{out[-3000:]}"
        assert session_members(pid) == [], what
        return took

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@pytest.mark.parametrize("node", sorted(NODES))
def test_a_node_stops_within_2_s_of_a_signal_at_any_moment(node, tmp_path):
    rng = random.Random(f"{SEED}-{node}")  # per node: one node's draws never shift another's
    first, second = rng.sample(SIGNALS, 2)
    waiting = Node(node, tmp_path / "waiting")
    try:
        assert waiting.up.wait(120), "".join(waiting.lines)[-3000:]
        time.sleep(rng.uniform(0.0, 0.5))
        waiting.stop(first, "while up and waiting")
    finally:
        waiting.kill()
    # a moment of its start-up: before the time the first one took to come up
    moment = rng.uniform(0.0, waiting.up_s)
    starting = Node(node, tmp_path / "starting")
    try:
        time.sleep(max(0.0, starting.t0 + moment - time.monotonic()))
        starting.stop(second, "while up" if starting.up.is_set() else "during start-up")
        print(f"{node}: {first.name} once up ({waiting.up_s:.2f} s), {second.name} "
              f"{moment:.2f} s after the start")
    finally:
        starting.kill()


def test_every_node_stops_within_2_s_of_a_signal_mid_episode(tmp_path):
    rng = random.Random(SEED)
    episodes = rng.randint(1, 3)  # the signals come a moment after this episode line
    moment = rng.uniform(0.0, 0.2)  # scripted episodes last 0.1-1 s in lockstep
    proc = subprocess.Popen(
        up_args("--router", "--log-dir", str(tmp_path), "--viz", f"save:{tmp_path}/run.rrd",
                "--episodes", "1000", "--policy", "scripted", "--verbose"),
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        preexec_fn=sigint_default)
    pids: dict[str, int] = {}
    lines: list[str] = []
    flying = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            if (node := launcher.started(line)) is not None:
                pids[node[0]] = node[1]
            elif line.startswith("episode ") and \
                    sum(x.startswith("episode ") for x in lines) == episodes:
                flying.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    stopped = False
    try:
        assert flying.wait(180), "".join(lines)[-3000:]
        assert set(pids) == {*NODES, "viz"}, pids
        time.sleep(moment)
        os.kill(proc.pid, signal.SIGSTOP)  # the launcher: no SIGTERM of its own meanwhile
        stopped = True
        order = rng.sample(sorted(pids), len(pids))
        sent = {}
        for node in order:
            sig = rng.choice(SIGNALS)
            sent[node] = (sig, time.monotonic())
            os.kill(pids[node], sig)
        took: dict[str, float] = {}
        deadline = time.monotonic() + LIMIT_S + 5
        while len(took) < len(pids) and time.monotonic() < deadline:
            for node, pid in pids.items():
                if node not in took and not alive(pid):
                    took[node] = time.monotonic() - sent[node][1]
            time.sleep(0.005)
        codes = {node: exit_status(pid) for node, pid in pids.items()}  # not reaped yet
        left = {node: session_members(pid) for node, pid in pids.items()}
        os.kill(proc.pid, signal.SIGCONT)
        stopped = False
        proc.wait(timeout=30)
        reader.join(5)
    finally:
        if stopped:
            os.kill(proc.pid, signal.SIGCONT)
        if proc.poll() is None:
            proc.kill()
    out = "".join(lines)
    what = {n: f"{s.name} {took.get(n, float('inf')):.2f} s, code {codes[n]}"
            for n, (s, _) in sent.items()}
    print(what)
    assert all(took.get(n, LIMIT_S) < LIMIT_S for n in pids), (what, out[-3000:])
    assert all(codes[n] in (0, 128 + sent[n][0]) for n in pids), (what, out[-3000:])
    assert not any(left.values()), left
    assert "Traceback" not in out, out[-3000:]
    assert "force-killed" not in out, out[-3000:]
    assert proc.returncode == 1, (proc.returncode, out[-3000:])  # nodes died: named
    assert "exited (code" in out, out[-3000:]


# A launcher (the real Graph.start) that dies in the race window: its child, between the
# fork and the prctl, SIGKILLs it and waits until reparented; then _pdeathsig goes on.
# The child's program (argv[2], as the interpreter) would sleep a minute.
LAUNCHER_DIES_BEFORE_PRCTL = """
import os, signal, sys, time
from skyloop import launcher

def launcher_dies_here():
    with open(sys.argv[1], "w") as f:
        f.write(str(os.getpid()))
    parent = os.getppid()
    os.kill(parent, signal.SIGKILL)
    while os.getppid() == parent:
        time.sleep(0.001)

launcher.block_until_started = launcher_dies_here
sys.executable = sys.argv[2]
launcher.Graph(dict(os.environ)).start("orphan", [])
"""


def test_a_child_whose_launcher_died_before_its_prctl_exits_at_once(tmp_path):
    """No parent-death signal comes to a child whose launcher died before its prctl:
    it sees that its parent is no longer the launcher and exits before it runs its
    program, instead of living on as an orphan."""
    pid_file, program = tmp_path / "child.pid", tmp_path / "program"
    program.write_text("#!/bin/sh\nexec sleep 60\n")
    program.chmod(0o755)
    fake = subprocess.run([sys.executable, "-c", LAUNCHER_DIES_BEFORE_PRCTL, str(pid_file),
                           str(program)], cwd=ROOT, stdin=subprocess.DEVNULL,
                          capture_output=True, text=True, timeout=60)
    assert fake.returncode == -signal.SIGKILL, (fake.returncode, fake.stderr[-3000:])
    pid = int(pid_file.read_text())
    try:
        deadline = time.monotonic() + LIMIT_S
        while alive(pid) and time.monotonic() < deadline:
            time.sleep(0.005)
        assert not alive(pid), Path(f"/proc/{pid}/cmdline").read_bytes()  # an orphan runs
        assert exit_status(pid) in (None, 128 + signal.SIGTERM)  # None: reaped already
    finally:
        if alive(pid):
            os.kill(pid, signal.SIGKILL)
