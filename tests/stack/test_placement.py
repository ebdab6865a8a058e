"""``skyloop.placement``: where ``skyloop up --pin`` puts the processes, and a real child
pinned by the launcher's pre-exec hook."""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from skyloop.placement import CHAIN, Placement, plan


def test_chain_gets_the_highest_cpu_and_the_rest_stay_free():
    p = plan("auto", lockstep=True, allowed={0, 1, 2, 3})
    assert p == Placement(frozenset({3}))
    assert all(p.cpus(n) == {3} for n in CHAIN)
    assert p.cpus("record") is None and p.cpus("viz") is None
    assert plan("chain", lockstep=False, allowed={2, 5}) == Placement(frozenset({5}))
    assert plan("chain", lockstep=True, beside=True, allowed={0, 1}) == Placement(
        frozenset({1}))


@pytest.mark.parametrize(("pin", "lockstep", "beside", "allowed"), [
    ("off", True, False, {0, 1}),     # asked not to
    ("auto", False, False, {0, 1}),   # real time: the scheduler keeps the choice
    ("auto", True, True, {0, 1}),     # a recorder or viewer beside: it may need the core
    ("auto", True, False, {3}),       # one usable core: nothing to separate
    ("chain", True, False, {0}),
])
def test_nothing_pinned(pin, lockstep, beside, allowed):
    assert plan(pin, lockstep, beside, allowed) is None


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs Linux and two usable CPUs")
def test_launcher_pins_a_child_before_exec():
    """The launcher's pre-exec hook pins the child program itself, threads included."""
    from skyloop.launcher import _preexec

    p = plan("chain", lockstep=True)
    assert p is not None
    code = ("import os, threading; seen = []; "
            "t = threading.Thread(target=lambda: seen.append(os.sched_getaffinity(0))); "
            "t.start(); t.join(); print(sorted(os.sched_getaffinity(0)), sorted(seen[0]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, preexec_fn=functools.partial(_preexec, os.getpid(), p.chain))
    assert out.stdout.split() == [str(sorted(p.chain))] * 2, out.stdout


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs Linux and two usable CPUs")
@pytest.mark.parametrize("recorded", [False, True], ids=["auto", "chain-router-recorder"])
def test_up_pins_the_lockstep_chain(tmp_path, recorded):
    """A real ``skyloop up`` in lockstep: ``--pin auto`` with nothing beside the chain, and
    ``--pin chain`` beside a recorder with the router in the chain: every node of the
    chain on the highest CPU the launcher may use (as the kernel says at "go"), the
    recorder free, the summary says so."""
    from loopback import up_args

    out = tmp_path / "summary.json"
    root = Path(__file__).resolve().parents[2]
    extra = ("--router", "--log-dir", str(tmp_path / "log"), "--pin", "chain") if recorded \
        else ()
    r = subprocess.run(up_args("--episodes", "1", "--policy", "scripted", "--json", str(out),
                               *extra), cwd=root, capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads(out.read_text())
    mine = sorted(os.sched_getaffinity(0))
    chain = ("sim", "perception", "policy", "bridge") + (("router",) if recorded else ())
    assert s["pinned"] and {n: s["cpus"][n] for n in chain} == {n: [mine[-1]] for n in chain}
    assert set(s["cpus"]) == set(chain) | ({"record"} if recorded else set()), s["cpus"]
    assert s["cpus"].get("record", mine) == mine, s["cpus"]
    assert f") shares CPU {mine[-1]}\n" in r.stdout, r.stdout
