"""The whole stack through ``skyloop up`` over real loopback Zenoh and UDP MAVLink.

One lockstep configuration (the shipped policy, 2 episodes) runs twice: as loopback
peers and through ``--router`` (a Python router, every node a client), each recording
an MCAP log. The tests check: the summary equals the in-process env's on the same
seeds; every action (float32) and every true position equals the env's; both logs hold
2 complete episodes; both runs put byte-identical payloads on the wire from the first
episode on (per topic, in order; ``status`` aside, and the ground phase before it: arm,
takeoff and offboard run on the wall clock). A separate run checks that killing a node
stops the launcher, naming it.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from loopback import alive, session_members, sigint_default, up_args

from bus import messages as m
from bus.log.reader import EpisodeLogReader, read_episodes
from skyloop import launcher

SEED, EPISODES = 1000, 2
ROOT = Path(__file__).resolve().parents[2]



def run_up(tmp: Path, name: str, *extra: str) -> tuple[dict, Path, str]:
    out = tmp / name
    cmd = up_args("--episodes", str(EPISODES), "--seed", str(SEED), "--log-dir", str(out),
                  "--json", str(out / "summary.json"), *extra)
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    mcaps = list(out.glob("*/*.mcap"))
    assert len(mcaps) == 1, proc.stdout
    return json.loads((out / "summary.json").read_text()), mcaps[0], proc.stdout


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("stack")
    return {"peer": run_up(tmp, "peer"), "router": run_up(tmp, "router", "--router")}


@pytest.fixture(scope="module")
def env_episodes():
    """The same episodes in the in-process env: actions, true positions, outcomes."""
    import torch

    from policy.training.env import UavNavEnv
    from policy.training.evaluate import make_controller

    torch.set_num_threads(1)
    controller = make_controller(None)
    env = UavNavEnv(scenario="valley")
    episodes = []
    for i in range(EPISODES):
        state, _ = env.reset(seed=SEED + i)
        actions, rewards, records, done, info = [], [], [], False, {}
        while not done:
            a = np.clip(np.asarray(controller(state), np.float64), -2, 2).astype(np.float32)
            actions.append(a)
            state, r, term, trunc, info = env.step(a)
            rewards.append(r)
            records.append(replace(info["record"], episode=i))
            done = term or trunc
        outcome = "collision" if info["collision"] else \
            "success" if info["goal_reached"] else "timeout"
        episodes.append({"actions": np.array(actions), "path": np.array(env.path),
                         "outcome": outcome, "steps": env.steps, "rewards": rewards,
                         "records": records})
    return episodes


@pytest.mark.slow
def test_summary_matches_env(runs, env_episodes):
    for summary, _, stdout in runs.values():
        assert summary["episodes"] == EPISODES
        for o in ("success", "collision", "timeout"):
            assert summary[o] == sum(e["outcome"] == o for e in env_episodes)
        assert summary["mean_steps"] == np.mean([e["steps"] for e in env_episodes])
        assert summary["steps_per_s"] > 0
        assert "summary:" in stdout and "log:" in stdout
        # CPU per control step of each node after "go" (skyloop.launcher, /proc)
        cpu = summary["cpu_ms_per_step"]
        assert all(cpu[n] > 0 for n in ("sim", "perception", "policy", "bridge")), cpu
        assert "record" in cpu and ("router" in cpu) == summary["router"], cpu
        assert "cpu per control step after go (ms): " in stdout
        # skyloop.placement, as the kernel reports each child's affinity at "go": with the
        # recorder beside the chain, --pin auto leaves every node free
        # (tests/stack/test_placement.py flies pinned chains)
        cpus, mine = summary["cpus"], sorted(os.sched_getaffinity(0))
        assert not summary["pinned"] and "pinned (--pin)" not in stdout, stdout
        assert set(cpus) == set(cpu) and all(v == mine for v in cpus.values()), cpus
        # each node's last line, summed per node: the bounded queues dropped nothing in
        # lockstep, and what they passed on is counted
        counters = summary["counters"]
        assert set(counters) == {"perception", "bridge", "record", "policy", "sim"}, counters
        assert all(c["dropped"] == 0 for c in counters.values()), counters
        # the policy answered every step, never held the vehicle, never sent a bad
        # action, its inboxes (observations, parameters) dropped nothing
        assert counters["policy"] == {"sent": summary["steps"], "refusals": 0,
                                      "bad_actions": 0, "dropped": 0,
                                      "dropped_observation": 0, "dropped_params": 0}, counters
        # the sim's inboxes: commands, goals, parameters
        assert counters["sim"] == {"dropped": 0, "dropped_cmd_vel": 0, "dropped_goal": 0,
                                   "dropped_params": 0}, counters
        assert counters["perception"]["published"] == summary["steps"], counters  # one a step
        assert counters["record"]["written"] > counters["perception"]["published"]
        assert "dropped from bounded queues (overload): bridge 0, perception 0, policy 0, " \
            "record 0, sim 0" in stdout


@pytest.mark.slow
def test_parity_actions_and_trajectory(runs, env_episodes):
    _, mcap, _ = runs["peer"]
    episodes, report = read_episodes(mcap)
    assert len(episodes) == EPISODES and all(e.complete for e in episodes), report.summary()
    by_stamp = {m.nanoseconds(c.header.stamp): c for c in
                (x.decode() for x in episode_messages(mcap) if x.name == "cmd_vel")}
    for ep, ref in zip(episodes, env_episodes, strict=True):
        assert ep.seed == SEED + ep.index and ep.steps == ref["steps"]
        assert ep.outcome == ref["outcome"]
        # Commands come from the bridge, events from the sim: the recorder may see the
        # last command after the END event, so commands are matched to steps by stamp.
        steps = [x.decode() for x in ep.topic("truth")]
        assert len(steps) == ref["steps"] + 1  # one per step, plus the terminal pose
        steps = steps[:-1]
        cmds = [m.setpoint_values(by_stamp[m.nanoseconds(t.header.stamp)]) for t in steps]
        np.testing.assert_array_equal(np.array(cmds, np.float32), ref["actions"])
        truth = np.array([m.odometry_values(t)[0] for t in steps])
        np.testing.assert_allclose(truth, ref["path"][: len(truth)], rtol=0, atol=1e-9)


@pytest.mark.slow
def test_stack_log_trains_from_logs(runs, env_episodes):
    from policy.algorithms.agents import make_goal_reward
    from policy.algorithms.replay import ReplayBuffer
    from policy.algorithms.rewards import RewardConfig
    from policy.logs.offline import load_logs

    _, mcap, _ = runs["peer"]
    buf = ReplayBuffer(10_000, (3, 35), 4)
    report = load_logs([mcap], buf, make_goal_reward("abr", RewardConfig()), RewardConfig())
    assert report.episodes_used == EPISODES, report.skipped
    assert report.transitions == sum(e["steps"] for e in env_episodes) == len(buf)


@pytest.mark.slow
def test_stack_step_records_are_the_envs_and_give_its_rewards(runs, env_episodes):
    """The sim publishes the episode core's record of every step; the recorder logs it;
    the records equal the env's (lockstep parity) and training from the log takes the
    env's rewards from them, the last step's included (whose observation the stack log
    lacks)."""
    from policy.algorithms.rewards import RewardConfig
    from policy.logs.offline import body_commands, episode_steps, file_observations, rebuild_episode

    _, mcap, _ = runs["peer"]
    episodes, _ = read_episodes(mcap)
    # as train --from-logs reads a log: the file's commands and observations by their
    # stamps and fields, since the bridge's last command of an episode can reach the
    # recorder after the sim's END (seen under load)
    commands, observations = body_commands(mcap), file_observations(mcap)
    for ep, ref in zip(episodes, env_episodes, strict=True):
        records = [m.step_record_values(x.decode()) for x in ep.topic("step_record")]
        assert records == ref["records"]
        assert episode_steps(ep).records is not None
        np.testing.assert_array_equal(
            rebuild_episode(ep, RewardConfig(), commands, observations).rewards,
            ref["rewards"])


def episode_messages(mcap: Path) -> list:
    """The log's messages from the first episode START on (file order), ``status``
    aside: before it the ground phase (the policy's zero setpoints while it arms and
    takes off) runs on the wall clock."""
    out, started = [], False
    for msg in EpisodeLogReader(mcap).messages():
        started = started or msg.name == "episode"
        if started and msg.name != "status":
            out.append(msg)
    return out


@pytest.mark.slow
def test_router_run_is_byte_identical(runs):
    def payloads(mcap: Path) -> dict[str, list[bytes]]:
        out: dict[str, list[bytes]] = {}
        for msg in episode_messages(mcap):  # per topic: one publisher, in order
            # the bus's topics; not the recorder's 3D view (/tf, viz/...), whose world
            # markers come when its worker has built the world
            if msg.name is not None:
                out.setdefault(msg.topic, []).append(msg.data)
        return out

    a, b = payloads(runs["peer"][1]), payloads(runs["router"][1])
    assert set(a) >= {"/skyloop/uav1/lidar/points", "/skyloop/uav1/cmd_vel",
                      "/skyloop/uav1/observation", "/skyloop/uav1/truth"}
    assert sum(len(v) for v in a.values()) > 1000
    assert a == b
    assert runs["router"][0]["router"] is True


def flying_graph() -> tuple[subprocess.Popen, dict[str, int]]:
    """``skyloop up`` for many episodes, returned once the first episode ended."""
    proc = subprocess.Popen(up_args("--episodes", "50", "--policy", "scripted"), cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=sigint_default)
    pids: dict[str, int] = {}
    assert proc.stdout is not None
    for line in proc.stdout:
        if (node := launcher.started(line)) is not None:
            pids[node[0]] = node[1]
        if line.startswith("episode "):  # the graph is flying
            break
    return proc, pids


def assert_all_gone(pids: dict[str, int]) -> None:
    for pid in pids.values():
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def watch_up(args: list[str], on_line, timeout: float = 60.0) -> tuple[int, str]:
    """Run ``skyloop up`` with ``args``; ``on_line(line, pids)`` sees each output line
    (``pids``: the newest pid of each node, from the "started" lines). Returns the exit
    code and the whole output."""
    proc = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    pids: dict[str, int] = {}
    lines: list[str] = []
    assert proc.stdout is not None
    try:
        for line in proc.stdout:
            lines.append(line)
            if (node := launcher.started(line)) is not None:
                pids[node[0]] = node[1]
            on_line(line, pids)
        proc.wait(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, "".join(lines)


@pytest.mark.timing
def test_child_death_stops_the_graph():
    proc, pids = flying_graph()
    try:
        assert set(pids) == {"perception", "bridge", "policy", "sim"}, pids
        os.kill(pids["perception"], signal.SIGKILL)
        t0 = time.monotonic()
        rest = proc.communicate(timeout=10)[0]
        assert time.monotonic() - t0 < 5.0
        assert proc.returncode != 0
        assert "'perception'" in rest and "last log line" in rest
        assert_all_gone(pids)
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.timing
@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)],
                         ids=["ctrl-c", "sigterm"])
def test_a_signal_stops_the_graph_with_a_summary(sig, code):
    proc, pids = flying_graph()
    try:
        proc.send_signal(sig)
        t0 = time.monotonic()
        rest = proc.communicate(timeout=10)[0]
        assert time.monotonic() - t0 < 5.0
        assert proc.returncode == code
        assert "summary: " in rest and "Traceback" not in rest, rest
        assert "force-killed" not in rest, rest  # every node stopped on its SIGTERM
        assert_all_gone(pids)
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.timing
def test_a_killed_launcher_leaves_no_child():
    """SIGKILL of ``skyloop up`` mid-run (nothing of its own runs): every child goes
    within 2 s, by its parent-death signal (``launcher._pdeathsig``), with whatever it
    started."""
    proc, pids = flying_graph()
    try:
        assert set(pids) == {"perception", "bridge", "policy", "sim"}, pids
        proc.kill()
        t0 = time.monotonic()
        proc.wait(5)
        gone: dict[str, float] = {}
        while len(gone) < len(pids) and time.monotonic() - t0 < 10:
            for name, pid in pids.items():
                if name not in gone and not alive(pid):  # gone, or a zombie of init's
                    gone[name] = time.monotonic() - t0
            time.sleep(0.005)
        assert set(gone) == set(pids) and max(gone.values()) < 2.0, gone
        assert all(session_members(pid) == [] for pid in pids.values())
    finally:
        if proc.poll() is None:
            proc.kill()
        for pid in pids.values():  # a survivor must not outlive the test either
            if alive(pid):
                os.killpg(pid, signal.SIGKILL)


@pytest.mark.timing
def test_the_launcher_names_the_nodes_it_had_to_force_kill(capsys):
    """What the graph tests' "force-killed" checks rest on: a child that ignores SIGTERM
    is SIGKILLed after the grace period and named; one that stops is not."""
    code = ("import signal, sys, time\n"
            "signal.signal(signal.SIGTERM, signal.SIG_IGN if sys.argv[1] == 'deaf' "
            "else signal.SIG_DFL)\nprint('ready', flush=True)\ntime.sleep(60)")
    children = [launcher.Child(name, subprocess.Popen(
        [sys.executable, "-c", code, name], stdout=subprocess.PIPE, text=True,
        start_new_session=True)) for name in ("deaf", "polite")]
    try:
        for c in children:
            assert c.proc.stdout.readline() == "ready\n"
        t0 = time.monotonic()
        assert launcher.Graph._stop(children, 0.5) == ["deaf"]
        assert time.monotonic() - t0 < 1.5
        assert children[0].proc.returncode == -signal.SIGKILL
        assert children[1].proc.returncode == -signal.SIGTERM
        err = capsys.readouterr().err
        assert "skyloop up: force-killed deaf (still running 0.5 s after SIGTERM)" in err, err
        assert launcher.Graph._stop(children[1:], 0.5) == []  # nothing left: no line
        assert "force-killed" not in capsys.readouterr().err
    finally:
        for c in children:
            if c.proc.poll() is None:
                c.proc.kill()
            c.proc.wait()


def test_cpu_time_of_a_child_is_read_until_it_is_reaped():
    """What ``cpu_ms_per_step`` rests on: an exited child keeps its CPU time in ``/proc``
    until it is reaped, and ``launcher.exited`` does not reap it."""
    proc = subprocess.Popen([sys.executable, "-c", "import time\nt = time.process_time()\n"
                             "while time.process_time() - t < 0.3: pass"])
    deadline = time.monotonic() + 60
    while not launcher.exited(proc):
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert proc.returncode is None  # not reaped
    cpu = launcher.cpu_seconds(proc.pid)
    assert cpu is not None and cpu >= 0.25
    assert proc.poll() == 0 and launcher.exited(proc)
    assert launcher.cpu_seconds(proc.pid) is None  # reaped: gone
    assert launcher.cpu_seconds(os.getpid()) > 0


def test_launcher_lines_match_nodes():
    from policy.nodes.node import READY_LINE
    from sitl.node.node import EPISODE_LINE, SUMMARY_LINE
    from sitl.node.node import READY_LINE as SIM_READY_LINE

    assert (launcher.EPISODE_LINE, launcher.SUMMARY_LINE, launcher.READY_LINE,
            launcher.SIM_READY_LINE) == (EPISODE_LINE, SUMMARY_LINE, READY_LINE, SIM_READY_LINE)


def test_realtime_run_reports_latency(tmp_path):
    out = tmp_path / "rt.json"
    proc = subprocess.run(up_args("--realtime", "--episodes", "1", "--max-steps", "20",
                                  "--policy", "scripted", "--json", str(out)),
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    s = json.loads(out.read_text())
    assert s["mode"] == "realtime" and s["episodes"] == 1
    assert s["steps"] <= 20
    assert 8.0 < s["steps_per_s"] < 11.0  # paced at 10 Hz
    assert 0.0 < s["latency_ms_p50"] <= s["latency_ms_p99"]
    assert "latency p50" in proc.stdout


def test_an_actor_that_outputs_nan_stops_the_stack_and_says_why(tmp_path):
    """Not a silent run of timeouts: the launcher, reading the actor for the state it was
    trained on (skyloop.launcher.as_trained), refuses it before any node starts, in one line
    naming the file (the policy node refuses such an actor at load time too, and in flight
    after a few non-finite actions: policy.nodes.node.MAX_BAD_ACTIONS)."""
    import torch

    from policy.algorithms.td3 import TD3, TD3Config

    agent = TD3(TD3Config())
    with torch.no_grad():
        agent.actor.net[0].weight.fill_(float("nan"))
    agent.save_actor(tmp_path / "nan.pt")
    out = subprocess.run(up_args("--episodes", "1", "--policy", str(tmp_path / "nan.pt")),
                         cwd=ROOT, capture_output=True, text=True, timeout=180)
    assert out.returncode == 2, out.stdout + out.stderr
    assert out.stderr.count("\n") == 1 and "nan.pt: the actor outputs" in out.stderr \
        and "NaN or inf" in out.stderr, out.stderr
    assert "started" not in out.stdout, out.stdout
    node = subprocess.run([sys.executable, "-m", "skyloop", "policy", "--policy",
                           str(tmp_path / "nan.pt")], cwd=ROOT, capture_output=True,
                          text=True, timeout=180)  # the node alone, as compose starts it
    assert node.returncode == 2 and "NaN or inf" in node.stderr, node.stderr


HOLD, LAND, CRASH, OFFBOARD = ("Failsafe: setpoints lost, holding", "Failsafe: landing",
                               "Collision: disarmed", "Offboard")  # commander event texts
TOL_S = 1e-6  # float time


class StatusEvents:
    """Every event text of uav1's ``status`` in order, each as (text, the status's
    ``vehicle_time``, its ``last_setpoint_time``: the vehicle time of the newest setpoint
    the commander had accepted)."""

    def __init__(self, bus) -> None:
        from bus import keys

        self.events: list[tuple[str, float, float]] = []
        bus.subscribe(keys.STATUS, "uav1", self.on_status)

    def on_status(self, msg) -> None:
        t, setpoint = float(msg.vehicle_time), float(msg.last_setpoint_time)
        self.events.extend((str(text), t, setpoint) for text in msg.event_texts)

    def texts(self, start: int, end: int | None = None) -> list[str]:
        return [text for text, _, _ in self.events[start:end]]


def assert_failsafe_timing(events: list[tuple[str, float, float]], loss_s: float,
                           hold_land_s: float) -> str | None:
    """The failsafe's timing in the vehicle's clock (as tests/sitl/test_vehicle_failsafe.py
    has it in lockstep): HOLD at the first control step after no setpoint came for
    COM_OF_LOSS_T (``loss_s``), LAND SKY_HOLD_LAND_T (``hold_land_s``) after HOLD, each to
    one control period; with no LAND, whatever ended the hold (a crash, the restarted
    policy's OFFBOARD) came before LAND was due. ``events``: :class:`StatusEvents`'
    from the kill to the restarted policy's OFFBOARD (included). The last setpoint is
    the one the vehicle says it took (the HOLD status's ``last_setpoint_time``); a status
    follows the step whose event it carries, so that step's time is the status's
    ``vehicle_time`` less a period. Returns what was seen, None if the vehicle crashed
    before any HOLD (nothing to time)."""
    from sitl.flight.vehicle import VehicleConfig

    period = VehicleConfig().control_period  # the sim's (its default)
    texts = [text for text, _, _ in events]
    if HOLD not in texts:
        return None
    i = texts.index(HOLD)
    hold, setpoint = events[i][1] - period, events[i][2]
    what = f"last setpoint at {setpoint:.2f} s, HOLD at {hold:.2f} s"
    assert math.isfinite(setpoint), what
    assert loss_s + TOL_S < hold - setpoint <= loss_s + period + TOL_S, what
    land = next((t - period for text, t, _ in events[i + 1:] if text == LAND), None)
    if land is None:  # the hold ended first (a status after its step, or during it)
        end = next(t for text, t, _ in events[i + 1:] if text in (CRASH, OFFBOARD))
        what += f", no LAND: the hold ended at {end:.2f} s"
        assert end - hold <= hold_land_s + period + TOL_S, what
    else:
        what += f", LAND at {land:.2f} s"
        assert hold_land_s - TOL_S <= land - hold <= hold_land_s + period + TOL_S, what
    return what


def test_chaos_random_kills_each_end_in_the_failsafe_and_a_restart(tmp_path):
    """Seeded chaos with ``--restart on-failure`` (bounded: 6 rounds; seed 7, or
    ``SKYLOOP_CHAOS_SEED``): SIGKILL each of policy, perception and bridge twice, in a
    random order, a random moment after an episode line, once the run flies again after
    the previous round. Each time the vehicle's failsafe acts (setpoints lost -> HOLD,
    then LAND, seen on the bus, on time in the vehicle's clock:
    :func:`assert_failsafe_timing`; or the vehicle crashed into what it was flying at,
    before or while braking) until the restarted policy takes over, the launcher names
    the node and restarts it (the policy with perception or the bridge: rest-for-one),
    the run finishes its episodes, the episodes in progress end ``aborted`` (never
    merged), and the log holds every episode whole."""
    from bus.node import Bus
    from bus.session import SessionConfig

    seed = int(os.environ.get("SKYLOOP_CHAOS_SEED", "7"))
    rng = np.random.default_rng(seed)
    # a kill lands a moment into the episode after an episode line (episodes of the
    # scripted policy last 0.1-1 s in lockstep)
    rounds = [(str(victim), float(rng.uniform(0, 0.3)))
              for victim in rng.permutation(["policy", "perception", "bridge"] * 2)]
    print("chaos seed", seed, "rounds", rounds)
    out = tmp_path / "chaos"
    loss_s, hold_land_s = 0.5, 0.3  # hold, land: well before a new policy
    args = up_args("--episodes", "30", "--policy", "scripted", "--restart", "on-failure",
                   "--max-restarts", "6",
                   "--log-dir", str(out), "--json", str(out / "summary.json"),
                   "--lockstep-timeout", "0.5", "--param", f"COM_OF_LOSS_T={loss_s}",
                   "--param", f"SKY_HOLD_LAND_T={hold_land_s}")
    hub = args[args.index("--hub") + 1]
    bus = Bus.open(SessionConfig(hub=hub))
    status = StatusEvents(bus)
    seen: list[int] = []  # len(status.events) at each kill
    flown = [0]  # episode lines since the last restart of the policy

    def on_line(line: str, pids: dict[str, int]) -> None:
        if line.startswith("started policy"):
            flown[0] = 0
        elif line.startswith("episode "):
            flown[0] += 1
            # the next kill once the run flies again: the aborted episode, then a whole
            # one since the last restart
            if flown[0] == 2 and len(seen) < len(rounds):
                victim, delay = rounds[len(seen)]
                seen.append(-1)  # filled in as the kill lands
                # a timer, not a sleep here: the run's lines keep flowing meanwhile
                threading.Timer(delay, kill, (len(seen) - 1, pids[victim])).start()

    def kill(k: int, pid: int) -> None:
        seen[k] = len(status.events)
        os.kill(pid, signal.SIGKILL)

    try:
        code, text = watch_up(args, on_line)
    finally:
        bus.close()
    assert code == 0, text
    assert len(seen) == len(rounds) and -1 not in seen, (seen, text)  # every kill landed in the run
    for k, (victim, _) in enumerate(rounds):
        assert f"node '{victim}' exited (code -9)" in text, (victim, text)
        end = seen[k + 1] if k + 1 < len(seen) else None
        after = status.texts(seen[k], end)
        cut = after.index(OFFBOARD) if OFFBOARD in after else \
            after.index(CRASH) + 1 if CRASH in after else len(after)
        # until the restarted policy took over the vehicle held, then landed; or it crashed
        # into what the scripted policy flew at, still on the last setpoint or braking in
        # the hold
        seq = [t for t in after[:cut] if t in (HOLD, LAND, CRASH)]
        assert seq[:1] == [CRASH] or seq[:2] in ([HOLD, LAND], [HOLD, CRASH]), (victim, after)
        # the restarted policy took over with a switch to OFFBOARD; but a vehicle that
        # crashed in OFFBOARD before any failsafe has its next episode placed in OFFBOARD
        # and, in lockstep, its clock stands still until the new policy's first command
        # comes: no failsafe and no switch then (the run going on shows the take-over)
        assert OFFBOARD in after or seq[:1] == [CRASH], (victim, after)
        print(victim, assert_failsafe_timing(status.events[seen[k]:seen[k] + cut + 1],
                                             loss_s, hold_land_s))
    assert "restarting it (1/6)" in text and "restarting it (2/6)" in text
    for needed in ("perception", "bridge"):
        assert f"restarting 'policy' too (it depends on '{needed}')" in text, text
    s = json.loads((out / "summary.json").read_text())
    assert s["episodes"] == 30 and s["aborted"] >= 1, s
    assert s["restarts"] == {"policy": 6, "perception": 2, "bridge": 2}, s
    [mcap] = list(out.glob("*/*.mcap"))
    episodes, report = read_episodes(mcap)
    assert report.clean and len(episodes) == 30 and all(e.complete for e in episodes), (
        report.summary(), [e.index for e in episodes], s["counters"].get("record"), s["cpus"])
    assert sum(e.outcome == "aborted" for e in episodes) == s["aborted"]


def test_a_killed_recorder_leaves_a_log_that_repair_makes_whole(tmp_path):
    """The recorder SIGKILLed mid-run (seeded moment): the launcher names it and stops
    (exit 1: the recorder is never restarted, a new one would be a second log), and
    ``skyloop log repair`` turns what it wrote into a finished log holding, whole and in
    order, every episode that ended before the kill but the last (whose END the recorder
    still held for late messages: ``end_grace_s``), as the launcher reported them."""
    rng = np.random.default_rng(11)
    kill_after = int(rng.integers(3, 8))  # episode lines
    out = tmp_path / "log"
    args = up_args("--episodes", "30", "--policy", "scripted", "--log-dir", str(out))
    reported: list[tuple[str, int]] = []  # (outcome, steps) per episode line

    def on_line(line: str, pids: dict[str, int]) -> None:
        if line.startswith("episode ") and len(reported) < kill_after:
            # "episode 3 (seed 1003): success in 58 steps, path 10.9 m"
            outcome, steps = line.split("): ", 1)[1].split()[0:3:2]
            reported.append((outcome, int(steps)))
            if len(reported) == kill_after:
                os.kill(pids["record"], signal.SIGKILL)

    code, text = watch_up(args, on_line)
    assert code == 1 and "node 'record' exited (code -9)" in text, text
    [src] = list(out.glob("*/*.mcap"))
    r = subprocess.run([sys.executable, "-m", "skyloop", "log", "repair", str(src), "--out",
                        str(tmp_path / "fixed")], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    [fixed] = list((tmp_path / "fixed").glob("*/*.mcap"))
    episodes, report = read_episodes(fixed)
    assert report.finished and f": {len(episodes)} complete, " in r.stdout, r.stdout
    assert len(episodes) >= kill_after - 1, (kill_after, len(episodes), r.stdout)
    assert [e.index for e in episodes] == list(range(len(episodes)))
    assert [(e.outcome, e.steps) for e in episodes] == reported[:len(episodes)]


def test_a_killed_policy_is_restarted_in_real_time(tmp_path):
    """The chaos test's fault in real time (10 Hz, the sim never waits for a command):
    the policy SIGKILLed mid-episode; the vehicle's failsafe holds (then lands), on time
    in the vehicle's clock (:func:`assert_failsafe_timing`), the launcher names the
    policy and starts it again, the new policy takes the vehicle again, the run finishes
    its episodes, the cut one ``aborted``, the log whole."""
    from bus.node import Bus
    from bus.session import SessionConfig

    out = tmp_path / "rt"
    loss_s, hold_land_s = 0.5, 1.0
    args = up_args("--realtime", "--episodes", "3", "--max-steps", "30", "--policy",
                   "scripted", "--restart", "on-failure", "--log-dir", str(out), "--json",
                   str(out / "summary.json"), "--param", f"COM_OF_LOSS_T={loss_s}",
                   "--param", f"SKY_HOLD_LAND_T={hold_land_s}")
    bus = Bus.open(SessionConfig(hub=args[args.index("--hub") + 1]))
    status = StatusEvents(bus)
    killed_at: list[int] = []

    def on_line(line: str, pids: dict[str, int]) -> None:
        if line.startswith("episode ") and not killed_at:  # a moment into the next one
            killed_at.append(len(status.events))
            threading.Timer(0.5, os.kill, (pids["policy"], signal.SIGKILL)).start()

    try:
        code, text = watch_up(args, on_line, timeout=120)
    finally:
        bus.close()
    assert code == 0, text
    assert "node 'policy' exited (code -9)" in text and "restarting it (1/3)" in text
    after = status.texts(killed_at[0])
    assert OFFBOARD in after, after  # the restarted policy took over
    cut = after.index(OFFBOARD)
    # until then the vehicle held (and landed, if the new policy came later than
    # SKY_HOLD_LAND_T), or crashed into what the scripted policy flew at
    seq = [t for t in after[:cut] if t in (HOLD, LAND, CRASH)]
    assert seq[:1] == [CRASH] or seq in ([HOLD], [HOLD, LAND]) or \
        seq[:2] in ([HOLD, LAND], [HOLD, CRASH]), after
    print(assert_failsafe_timing(status.events[killed_at[0]:killed_at[0] + cut + 1], loss_s,
                                 hold_land_s))
    s = json.loads((out / "summary.json").read_text())
    # once, under a second test worker's load, the restarted policy was restarted again
    # (cause not found yet): the run must still go on
    assert s["mode"] == "realtime" and set(s["restarts"]) == {"policy"}, (s, text[-3000:])
    assert s["episodes"] == 3 and s["aborted"] >= 1, s
    [mcap] = list(out.glob("*/*.mcap"))
    episodes, report = read_episodes(mcap)
    assert report.clean and len(episodes) == 3 and all(e.complete for e in episodes)
    assert sum(e.outcome == "aborted" for e in episodes) == s["aborted"]


def test_a_restarted_router_lets_the_run_go_on(tmp_path):
    """``--router --restart on-failure``: the router SIGKILLed mid-run is started again on
    its endpoint, the Zenoh clients reconnect by themselves, the policy rejoins, and
    the run finishes; every episode that ended other than ``aborted`` is whole in the
    log (the recorder is a client too), but the one whose end was in flight as the
    router died."""
    out = tmp_path / "router"
    ended: list[str] = []

    def on_line(line: str, pids: dict[str, int]) -> None:
        if line.startswith("episode "):
            ended.append(line)
            if len(ended) == 2:  # as episode 2 starts
                os.kill(pids["router"], signal.SIGKILL)

    code, text = watch_up(up_args("--router", "--episodes", "8", "--policy", "scripted",
                                  "--restart", "on-failure", "--lockstep-timeout", "0.5",
                                  "--log-dir", str(out), "--json", str(out / "s.json")),
                          on_line)
    assert code == 0, text
    assert "node 'router' exited (code -9)" in text
    s = json.loads((out / "s.json").read_text())
    assert s["episodes"] == 8 and s["restarts"] == {"router": 1, "policy": 1}, s
    assert s["aborted"] >= 1, text  # the episode the outage cut
    outcomes = {int(x.split()[1]): x.split(": ")[1].split()[0] for x in ended}
    [mcap] = list(out.glob("*/*.mcap"))
    logged = {e.index: e for e in read_episodes(mcap)[0]}
    for i, outcome in outcomes.items():
        # episode 1 ended as the router died: its last messages may have been in flight
        # through it (lost with it, as on any broker); every other one is whole
        if outcome != "aborted" and i != 1:
            assert logged[i].complete and logged[i].outcome == outcome, (i, text)


def test_started_lines_parse():
    line = launcher.STARTED_LINE.format(name="perception", pid=4242)
    assert launcher.started(line) == ("perception", 4242)
    assert launcher.started(line + "\n") == ("perception", 4242)
    for other in ("started", "started sim", "started sim (pid x)", "episode 0 (seed 1)"):
        assert launcher.started(other) is None
