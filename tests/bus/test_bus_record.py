"""bus.log.record over real Zenoh on loopback: a fake run of every topic type published from
one session is recorded by another into MCAP and read back with matching counts; bad
payloads and a full queue are counted; run_record and ``skyloop record``; a SIGKILLed
recorder process loses at most the episode in progress."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from collections import Counter
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from loopback import free_port, wait_for
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from bus import keys
from bus import messages as m
from bus.log.record import Recorder, run_record
from bus.log.writer import EpisodeLogWriter, read_episodes
from bus.node import Bus
from bus.session import SessionConfig, open_session

REPO = Path(__file__).resolve().parents[2]
SCAN = np.random.default_rng(0).normal(scale=10, size=(28_800, 3)).astype(np.float32)




class FakeRun:
    """Publishers for every topic of one vehicle and a scripted run."""

    def __init__(self, bus: Bus, vehicle: str = "uav1") -> None:
        self.vehicle = vehicle
        self.pubs = {t: bus.publisher(t, vehicle) for t in keys.TOPICS}
        self.sent: Counter[str] = Counter()

    def wait_matched(self, timeout: float = 10.0) -> None:
        for topic, pub in self.pubs.items():
            assert pub.wait_matched(timeout), f"nobody subscribes {topic}"

    def put(self, topic, msg):
        self.pubs[topic].put(msg)
        self.sent[topic] += 1

    def episode(self, ep: int, steps: int = 4, end: bool = True) -> None:
        self.put(keys.EPISODE, m.episode_start(ep, 7 + ep, (0, 0, 1), (20, 0, 1), 0.0, "valley"))
        self.put(keys.GOAL, m.pose_stamped((20, 0, 1), 0.0))
        for s in range(steps):
            t = 0.1 * s
            self.put(keys.CLOCK, m.step_clock(s, t, ep))
            self.put(keys.LIDAR_POINTS, m.pointcloud(SCAN, t))
            self.put(keys.ODOM, m.odometry((s, 0, 1), (1, 0, 0), (0, 0, 0, 1), t))
            self.put(keys.TRUTH, m.odometry((s, 0, 1), (1, 0, 0), (0, 0, 0, 1), t))
            self.put(keys.OBSERVATION, m.observation(np.full((3, 35), s, np.float32), t, ep, s))
            self.put(keys.CMD_VEL, m.velocity_setpoint((1.0, 0.0, 0.0), 0.0, t, body=False))
        if end:
            self.put(keys.EPISODE, m.episode_end(ep, "success", steps, 0.1 * steps))

    def actor(self, version: int) -> None:
        self.put(keys.ACTOR, m.actor_weights(b"\x01" * 1000, version))


def test_recorder_writes_every_topic(tmp_path):
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    bus = Bus.open(cfg)
    rec_session = open_session(cfg)
    writer = EpisodeLogWriter(tmp_path, "rec")
    recorder = Recorder(rec_session, writer)
    try:
        run = FakeRun(bus)
        run.wait_matched()
        run.episode(0)
        run.actor(1)
        run.episode(1)
        bus.session.put("skyloop/uav1/odom", b"not cdr")  # counted, not written
        bus.session.put("skyloop/uav1/bogus", b"\x00\x01\x00\x00")  # unknown topic
        total = sum(run.sent.values())
        assert recorder.wait_written(total, timeout=20.0)
        wait_for(lambda: recorder.counters()["received"] == total + 2, what="bad payloads")
        counters = recorder.stop()
    finally:
        recorder.stop()
        bus.close()
        rec_session.close()
    assert counters["written"] == total and counters["dropped"] == 0
    assert counters["undecodable"] == 1 and counters["unknown_topic"] == 1
    assert counters["episodes_started"] == counters["episodes_ended"] == 2
    eps, rep = read_episodes(writer.dir)
    assert rep.clean and rep.messages == total and rep.outside_episodes == 1  # the actor
    assert [(e.index, e.seed, e.outcome, e.steps) for e in eps] == [(0, 7, "success", 4),
                                                                    (1, 8, "success", 4)]
    per_topic = Counter(x.name for e in eps for x in e.messages) + Counter({keys.ACTOR: 1})
    assert per_topic == run.sent
    scan = m.points_from_pointcloud(eps[1].topic(keys.LIDAR_POINTS)[-1].decode())
    np.testing.assert_array_equal(scan, SCAN)
    with AnyReader([writer.dir]) as ar:
        counts = {c.topic: c.msgcount for c in ar.connections}
    assert counts == {keys.ros_topic("uav1", t): n for t, n in run.sent.items()}


@contextmanager
def sim_and_perception(tmp_path: Path, name: str, end_grace_s: float):
    """A recorder and two publishing sessions on separate Zenoh links (the sim's run and
    perception's observation publisher), both matched; episode 0 (3 steps) recorded.
    Yields (recorder, writer, run, obs); closes everything after."""
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    sim, perception = Bus.open(cfg), Bus.open(cfg)
    rec_session = open_session(cfg)
    writer = EpisodeLogWriter(tmp_path, name)
    recorder = Recorder(rec_session, writer, end_grace_s=end_grace_s)
    try:
        run = FakeRun(sim)
        obs = perception.publisher(keys.OBSERVATION, "uav1")
        run.wait_matched()
        assert obs.wait_matched(10.0)
        run.episode(0, steps=3)  # its END is now on the wire
        wait_for(lambda: recorder.counters()["received"] == sum(run.sent.values()),
                 what="episode 0 received")
        yield recorder, writer, run, obs
    finally:
        recorder.stop()
        sim.close()
        perception.close()
        rec_session.close()


def test_a_late_step_message_stays_in_its_episode(tmp_path):
    """Two processes: the sim's END overtakes perception's last observation (separate
    Zenoh links). The recorder holds the END until the next START, so the observation is
    in its episode, and what is not a step topic (actor weights) stays between episodes;
    the last episode's END is written within the grace time."""
    with sim_and_perception(tmp_path, "late", end_grace_s=2.0) as (recorder, writer, run, obs):
        obs.put(m.observation(np.zeros((3, 35), np.float32), 0.3, 0, 3))  # after END 0
        # received before the next START (two sessions: under load it could otherwise
        # come after it: test_an_early_step_message_goes_to_its_episode)
        wait_for(lambda: recorder.counters()["received"] == sum(run.sent.values()) + 1,
                 what="the late observation received")
        run.actor(1)
        run.episode(1, steps=2)
        total = sum(run.sent.values()) + 1
        assert recorder.wait_written(total - 1, timeout=20.0)  # all but the held last END
        assert recorder.counters()["episodes_ended"] == 1
        assert recorder.wait_written(total, timeout=20.0)  # the grace time let it go
    eps, rep = read_episodes(writer.dir)
    assert rep.clean and rep.outside_episodes == 1  # the actor weights
    assert [len(e.topic(keys.OBSERVATION)) for e in eps] == [4, 2]
    assert [int(x.decode().step) for x in eps[0].topic(keys.OBSERVATION)] == [0, 1, 2, 3]


def test_an_early_step_message_goes_to_its_episode(tmp_path):
    """The other order: perception's first observation of episode 1 overtakes the sim's
    START (the sim's link busy with point clouds). While END 0 is held, a step message
    naming episode 1 waits for START 1 and is written after it, not into episode 0."""
    with sim_and_perception(tmp_path, "early", end_grace_s=5.0) as (recorder, writer, run, obs):
        obs.put(m.observation(np.ones((3, 35), np.float32), 0.4, 1, 0))  # before START 1
        wait_for(lambda: recorder.counters()["received"] == sum(run.sent.values()) + 1,
                 what="the early observation received")
        run.episode(1, steps=2)
        assert recorder.wait_written(sum(run.sent.values()), timeout=20.0)
    eps, rep = read_episodes(writer.dir)
    assert rep.clean and rep.outside_episodes == 0
    assert [len(e.topic(keys.OBSERVATION)) for e in eps] == [3, 3]
    assert {int(x.decode().episode) for x in eps[0].topic(keys.OBSERVATION)} == {0}
    assert {int(x.decode().episode) for x in eps[1].topic(keys.OBSERVATION)} == {1}
    assert eps[1].messages[0].name == keys.EPISODE  # START first, then the early one
    assert eps[1].messages[1].name == keys.OBSERVATION


class GatedWriter(EpisodeLogWriter):
    """A writer stuck until the gate opens: the recorder's queue must overflow."""

    gate = threading.Event()

    def write(self, *args, **kwargs):
        self.gate.wait(10.0)
        super().write(*args, **kwargs)


def test_full_queue_is_a_counted_drop(tmp_path):
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    with Bus.open(cfg) as bus:
        session = open_session(cfg)
        writer = GatedWriter(tmp_path, "gated")
        recorder = Recorder(session, writer, vehicle="uav1", queue_size=2)
        try:
            pub = bus.publisher(keys.ODOM, "uav1")
            other = bus.publisher(keys.ODOM, "uav2")  # not this recorder's vehicle
            assert pub.wait_matched(10.0)
            for i in range(10):
                pub.put(m.odometry((i, 0, 0), (0, 0, 0), (0, 0, 0, 1), i))
                other.put(m.odometry((i, 0, 0), (0, 0, 0), (0, 0, 0, 1), i))
            wait_for(lambda: recorder.counters()["received"] == 10, what="10 messages")
            writer.gate.set()
            counters = recorder.stop()
        finally:
            writer.gate.set()
            recorder.stop()
            session.close()
    assert counters["dropped"] >= 7 and counters["written"] + counters["dropped"] == 10
    _, rep = read_episodes(writer.dir)
    assert rep.messages == counters["written"]


def test_run_record_until_stopped(tmp_path):
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    stop, ready, result = threading.Event(), threading.Event(), []
    thread = threading.Thread(target=lambda: result.append(run_record(
        tmp_path, cfg, stop, vehicle="uav1", run_name="rr", ready=ready)))
    thread.start()
    try:
        assert ready.wait(10.0)
        with Bus.open(cfg) as bus:
            run = FakeRun(bus)
            run.wait_matched()
            run.episode(0, steps=2)
            run.episode(1, steps=2)
            # both END events flushed their episode to disk: readable while recording
            wait_for(lambda: read_episodes(tmp_path / "rr")[1].episodes_complete == 2,
                     what="two episodes on disk")
    finally:
        stop.set()
        thread.join(20.0)
    assert not thread.is_alive()
    (res,) = result
    assert res.path == tmp_path / "rr" and (res.path / "metadata.yaml").exists()
    assert res.counters["written"] == sum(run.sent.values()) and res.counters["dropped"] == 0
    with open(res.path / "rr_0.mcap", "rb") as f:  # zstd chunks unless asked otherwise
        chunks = make_reader(f).get_summary().chunk_indexes
    assert chunks and {c.compression for c in chunks} == {"zstd"}


def test_main_help(capsys):
    from skyloop.cli.tools import parse_tool

    with pytest.raises(SystemExit) as exc:
        parse_tool(["record", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "--out" in out and "--vehicle" in out and "skyloop record" in out
    assert parse_tool(["record"]).compression == "zstd"
    assert parse_tool(["record", "--compression", "none"]).compression == "none"


def test_sigkilled_recorder_loses_at_most_the_open_episode(tmp_path):
    hub = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, "PYTHONPATH": str(REPO), "SKYLOOP_ZENOH_HUB": hub}
    with Bus.open(SessionConfig(hub=hub)) as bus:
        proc = subprocess.Popen(
            [sys.executable, "-m", "skyloop", "record", "--out", str(tmp_path), "--run-name",
             "k", "--vehicle", "uav1"], cwd=REPO, env=env,
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            run = FakeRun(bus)
            run.wait_matched(30.0)  # the recorder process is up and subscribed
            run.episode(0)
            run.episode(1)
            wait_for(lambda: read_episodes(tmp_path / "k")[1].episodes_complete == 2,
                     what="two episodes on disk")
            run.episode(2, end=False)
        finally:
            proc.kill()  # SIGKILL mid-episode
            proc.wait(10)
    eps, rep = read_episodes(tmp_path / "k", include_incomplete=True)
    assert [(e.index, e.complete) for e in eps][:2] == [(0, True), (1, True)]
    assert rep.episodes_complete == 2 and rep.episodes_incomplete <= 1
    assert not rep.finished and not (tmp_path / "k" / "metadata.yaml").exists()
