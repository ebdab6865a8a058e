"""bus.log.writer: the MCAP episode log opens with the mcap reader and with rosbags; the
episode reader groups, reports incomplete episodes, and survives SIGKILL, truncation
and corruption with a count of what was lost."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader as Rosbag2Reader

from bus import keys
from bus import messages as m
from bus.log.mcap_scan import CHUNK, MAGIC, records
from bus.log.reader import log_files
from bus.log.writer import (
    EpisodeLogReader,
    EpisodeLogWriter,
    LogReadError,
    read_episodes,
    recover_log,
)

REPO = Path(__file__).resolve().parents[2]
PTS = np.random.default_rng(0).normal(scale=10, size=(2000, 3)).astype(np.float32)
STEPS = 6
PER_EPISODE = 2 + 3 * STEPS  # START, END, and lidar + odom + cmd_vel per step


def write_episode(w, ep, t, vehicle="uav1", end=True, steps=STEPS):
    w.write_msg(vehicle, keys.EPISODE, m.episode_start(ep, 100 + ep, (0, 0, 1), (9, 0, 1), 0.0), t)
    for s in range(steps):
        t += 1
        w.write_msg(vehicle, keys.LIDAR_POINTS, m.pointcloud(PTS + ep, 0.1 * s), t)
        w.write_msg(vehicle, keys.ODOM, m.odometry((s, ep, 1), (1, 0, 0), (0, 0, 0, 1), 0.1 * s), t)
        w.write_msg(vehicle, keys.CMD_VEL,
                    m.velocity_setpoint((1, 0, 0), 0.1 * ep, 0.1 * s, body=False), t)
    if end:
        outcome = ("success", "collision", "timeout")[ep % 3]
        w.write_msg(vehicle, keys.EPISODE, m.episode_end(ep, outcome, steps, 0.1 * steps), t + 1)
    return t + 2


def make_run(out, name="run", episodes=3, compression="none", chunk_size=64 * 1024):
    with EpisodeLogWriter(out, name, compression=compression, chunk_size=chunk_size) as w:
        t = 1_000
        for ep in range(episodes):
            t = write_episode(w, ep, t)
            w.write_msg("uav1", keys.ACTOR, m.actor_weights(b"w" * 100, ep + 1), t)
    return w.dir


# ------------------------------------------------------------------ standard readers
@pytest.mark.parametrize("compression", ["none", "zstd", "lz4"])
def test_opens_with_mcap_and_rosbags(tmp_path, compression):
    run = make_run(tmp_path, compression=compression)
    assert sorted(p.name for p in run.iterdir()) == ["metadata.yaml", "run_0.mcap"]
    expected = {"/skyloop/uav1/episode": 6, "/skyloop/uav1/lidar/points": 3 * STEPS,
                "/skyloop/uav1/odom": 3 * STEPS, "/skyloop/uav1/cmd_vel": 3 * STEPS,
                "/skyloop/uav1/actor": 3}
    with open(run / "run_0.mcap", "rb") as f:
        reader = make_reader(f)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        counts = summary.statistics.channel_message_counts
        assert {c.topic: counts[i] for i, c in summary.channels.items()} == expected
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        for schema in summary.schemas.values():
            assert schema.encoding == "ros2msg"
            assert schema.data.decode() == m.msgdef(schema.name)
        names = [md.name for md in reader.iter_metadata()]
        assert names.count("skyloop.episode") == 3 and "skyloop.run" in names
        assert "rosbag2" in names
        assert sum(1 for _ in reader.iter_messages()) == sum(expected.values())
    for path in (run, run / "run_0.mcap"):  # the rosbag2 directory and the bare file
        with AnyReader([path]) as ar:
            assert {c.topic: c.msgcount for c in ar.connections} == expected
            types = {c.topic: c.msgtype for c in ar.connections}
            assert types["/skyloop/uav1/episode"] == m.EPISODE_EVENT
            clouds = [ar.deserialize(raw, c.msgtype) for c, _, raw in ar.messages()
                      if c.msgtype == m.POINTCLOUD2]
            assert len(clouds) == 3 * STEPS
            np.testing.assert_array_equal(m.points_from_pointcloud(clouds[-1]), PTS + 2)
    with Rosbag2Reader(run) as bag:  # metadata.yaml
        assert bag.message_count == sum(expected.values())
        assert {t: i.msgcount for t, i in bag.topics.items()} == expected



def test_default_chunks_are_zstd_and_read_back_exactly(tmp_path):
    """The writer's default (what the recorder and `skyloop up --log-dir` write): zstd
    chunks, which the episode reader reads back byte for byte."""
    with EpisodeLogWriter(tmp_path, "default", chunk_size=64 * 1024) as w:
        t = 1_000
        for ep in range(2):
            t = write_episode(w, ep, t)
    with open(w.path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) >= 2 and {c.compression for c in chunks} == {"zstd"}
    eps, rep = read_episodes(w.dir)
    assert rep.clean and [(e.index, e.seen) for e in eps] == [(0, PER_EPISODE), (1, PER_EPISODE)]
    clouds = eps[1].topic(keys.LIDAR_POINTS)
    assert len(clouds) == STEPS
    np.testing.assert_array_equal(m.points_from_pointcloud(clouds[-1].decode()), PTS + 1)

def test_zstd_chunks_are_written_at_the_log_level(tmp_path):
    """mcap's writer compresses its chunks with ``zstandard.compress`` (level 3, no
    option); ``bus.log.writer`` stands in for it at ``ZSTD_LEVEL`` (issue 11, "Speed")."""
    import mcap.writer
    import zstandard

    from bus.log import writer as log

    assert isinstance(mcap.writer.zstandard, log._McapZstd)
    data = m.encode(m.pointcloud(PTS, 1.0)) * 20
    assert mcap.writer.zstandard.compress(data) == \
        zstandard.ZstdCompressor(level=log.ZSTD_LEVEL).compress(data)
    with EpisodeLogWriter(tmp_path, "level") as w:
        write_episode(w, 0, 1_000)
    with open(w.path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert {c.compression for c in chunks} == {"zstd"}
    eps, rep = read_episodes(w.dir)
    assert rep.clean and [e.seen for e in eps] == [PER_EPISODE]


def test_split_every_n_episodes_never_splits_an_episode(tmp_path):
    """``split_episodes=2``: 5 episodes in 3 files (2, 2, 1), each a finished MCAP of
    whole episodes; metadata.yaml lists the three and rosbags reads the directory as
    one bag."""
    with EpisodeLogWriter(tmp_path, "run", split_episodes=2) as w:
        t = 1_000
        for ep in range(5):
            t = write_episode(w, ep, t)
            if ep == 2:  # between episodes: messages outside any episode stay in order
                w.write_msg("uav1", keys.ACTOR, m.actor_weights(b"w", 1), t)
    files = sorted(w.dir.glob("*.mcap"))
    assert [f.name for f in files] == ["run_0.mcap", "run_1.mcap", "run_2.mcap"]
    per_file = []
    for f in files:
        episodes, report = read_episodes(f)
        assert report.clean and all(e.complete for e in episodes)
        per_file.append([e.index for e in episodes])
        with open(f, "rb") as fh:  # finished: summary and footer
            assert make_reader(fh).get_summary() is not None
    assert per_file == [[0, 1], [2, 3], [4]]
    with Rosbag2Reader(w.dir) as bag:  # metadata.yaml lists all three, in order
        assert bag.message_count == 5 * PER_EPISODE + 1
        assert sum(1 for _ in bag.messages()) == 5 * PER_EPISODE + 1
    with AnyReader([w.dir]) as ar:
        assert sum(1 for _ in ar.messages()) == 5 * PER_EPISODE + 1
    assert log_files(w.dir) == files
    with pytest.raises(LogReadError, match="holds 3 .mcap files"):  # never just the first
        read_episodes(w.dir)
    with pytest.raises(ValueError, match="split_episodes"):
        EpisodeLogWriter(tmp_path, "bad", split_episodes=-1)


class FakeClock:
    """A ``clock`` for the writer: seconds that pass only when the test says so."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _episodes_per_file(run_dir):
    out = []
    for f in sorted(run_dir.glob("*.mcap")):
        episodes, report = read_episodes(f)
        assert report.clean and all(e.complete for e in episodes), f
        with open(f, "rb") as fh:  # finished: summary and footer
            assert make_reader(fh).get_summary() is not None
        out.append([(e.vehicle, e.index) for e in episodes])
    return out


def test_split_every_m_minutes_at_the_first_episode_end_after_them(tmp_path):
    """``split_minutes=1``: a file is finished at the first episode end once 60 s of
    the writer's clock have passed since the file began (its first message), never
    before and never inside an episode, however long the episode; metadata.yaml lists
    every file and rosbags reads them as one bag."""
    clock = FakeClock()
    with EpisodeLogWriter(tmp_path, "run", split_minutes=1, clock=clock) as w:
        t = 1_000
        for ep, at in enumerate((0.0, 59.9, 60.0,  # file 0 began at 0: split after ep 2
                                 100.0, 159.0, 170.0,  # file 1 began at 100 (ep 3)
                                 1_000.0)):  # file 2 began at 1000; closed by close()
            clock.now = at
            t = write_episode(w, ep, t)
        assert w.next_file_index == 2
        # 10 minutes inside episode 7 (one in file 2): still one file, split at its end
        t = write_episode(w, 7, t, end=False)
        clock.now = 1_600.0
        w.write_msg("uav1", keys.EPISODE, m.episode_end(7, "success", STEPS, 1.0), t)
        assert w.next_file_index == 3 and len(w.files) == 3
    assert [f.name for f in sorted(w.dir.glob("*.mcap"))] == \
        ["run_0.mcap", "run_1.mcap", "run_2.mcap"]
    assert _episodes_per_file(w.dir) == [[("uav1", 0), ("uav1", 1), ("uav1", 2)],
                                         [("uav1", 3), ("uav1", 4), ("uav1", 5)],
                                         [("uav1", 6), ("uav1", 7)]]
    with Rosbag2Reader(w.dir) as bag:
        assert bag.message_count == 8 * PER_EPISODE
    for i, bad in enumerate((-1, -0.5, float("nan"), float("inf"))):
        with pytest.raises(ValueError, match="split_minutes"):
            EpisodeLogWriter(tmp_path, f"bad{i}", split_minutes=bad)


def test_split_minutes_waits_for_every_vehicle_and_counts_with_split_episodes(tmp_path):
    """Two vehicles: past the minutes, uav1's episode end does not split while uav2's
    episode is open; uav2's end does. With ``split_episodes`` too, whichever comes
    first splits."""
    clock = FakeClock()
    with EpisodeLogWriter(tmp_path, "two", split_minutes=1, clock=clock) as w:
        t = write_episode(w, 0, 1_000, vehicle="uav2", end=False)  # uav2's episode opens
        clock.now = 61.0
        t = write_episode(w, 0, t, vehicle="uav1")  # uav1's ends past 60 s: uav2's open
        assert w.next_file_index == 0
        w.write_msg("uav2", keys.EPISODE, m.episode_end(0, "success", STEPS, 1.0), t)
        assert w.next_file_index == 1  # every episode closed: the split
        t = write_episode(w, 1, t + 1, vehicle="uav1")
    assert _episodes_per_file(w.dir) == [[("uav1", 0), ("uav2", 0)], [("uav1", 1)]]

    clock = FakeClock()
    with EpisodeLogWriter(tmp_path, "both", split_minutes=1, split_episodes=3,
                          clock=clock) as w:
        t = 1_000
        for ep, at in enumerate((0.0, 61.0,  # 2 episodes in 61 s: split by time
                                 70.0, 71.0, 72.0,  # 3 in 2 s: split by count
                                 80.0)):
            clock.now = at
            t = write_episode(w, ep, t)
    assert [len(f) for f in _episodes_per_file(w.dir)] == [2, 3, 1]


# ------------------------------------------------------------------ episodes
def test_reader_groups_episodes(tmp_path):
    eps, rep = read_episodes(make_run(tmp_path))
    assert [(e.index, e.outcome, e.steps, e.seed) for e in eps] == [
        (0, "success", STEPS, 100), (1, "collision", STEPS, 101), (2, "timeout", STEPS, 102)]
    for e in eps:
        assert e.complete and e.seen == e.expected == PER_EPISODE
        assert len(e.topic(keys.ODOM)) == STEPS
        yaw_rates = [m.setpoint_values(x.decode())[3] for x in e.topic(keys.CMD_VEL)]
        assert yaw_rates == [0.1 * e.index] * STEPS
    assert rep.clean and rep.messages == 3 * PER_EPISODE + 3 and rep.messages_lost == 0
    assert rep.outside_episodes == 3  # the actor weights between episodes
    eps, _ = read_episodes(tmp_path / "run", topics={keys.ODOM})
    assert {x.name for e in eps for x in e.messages} == {keys.ODOM}
    assert all(e.seen == PER_EPISODE for e in eps)


def test_interleaved_vehicles(tmp_path):
    with EpisodeLogWriter(tmp_path, "two") as w:
        w.write_msg("uav1", keys.EPISODE, m.episode_start(0, 1, (0, 0, 0), (1, 0, 0), 0.0))
        w.write_msg("uav2", keys.EPISODE, m.episode_start(0, 2, (0, 0, 0), (1, 0, 0), 0.0))
        for s in range(4):
            for v in ("uav1", "uav2"):
                w.write_msg(v, keys.ODOM, m.odometry((s, 0, 0), (0, 0, 0), (0, 0, 0, 1), s))
        w.write_msg("uav2", keys.EPISODE, m.episode_end(0, "collision", 4, 0.4))
        w.write_msg("uav1", keys.EPISODE, m.episode_end(0, "success", 4, 0.4))
    eps, rep = read_episodes(w.dir)
    assert [(e.vehicle, e.outcome, e.seed, len(e.topic(keys.ODOM))) for e in eps] == [
        ("uav2", "collision", 2, 4), ("uav1", "success", 1, 4)]
    assert rep.clean


def test_closed_mid_episode_is_incomplete(tmp_path):
    with EpisodeLogWriter(tmp_path, "cut") as w:
        t = write_episode(w, 0, 1)
        write_episode(w, 1, t, end=False)
    eps, rep = read_episodes(w.dir)
    assert [e.index for e in eps] == [0]
    assert rep.finished and (rep.episodes_complete, rep.episodes_incomplete) == (1, 1)
    eps, _ = read_episodes(w.dir, include_incomplete=True)
    assert eps[1].problem.startswith("no END") and eps[1].outcome is None


# ------------------------------------------------------------------ crash and damage
WRITER = """
import sys, time
import numpy as np
from bus import keys, messages as m
from bus.log.writer import EpisodeLogWriter
pts = np.random.default_rng(0).normal(size=(2000, 3)).astype(np.float32)
w = EpisodeLogWriter(sys.argv[1], "killed", chunk_size=64 * 1024)
t = 1
for ep in range(3):
    w.write_msg("uav1", keys.EPISODE, m.episode_start(ep, ep, (0, 0, 1), (9, 0, 1), 0.0), t)
    for s in range(10):
        t += 1
        w.write_msg("uav1", keys.LIDAR_POINTS, m.pointcloud(pts, s), t)
        w.write_msg("uav1", keys.ODOM, m.odometry((s, 0, 1), (1, 0, 0), (0, 0, 0, 1), s), t)
    if ep < 2:
        w.write_msg("uav1", keys.EPISODE, m.episode_end(ep, "success", 10, 1.0), t)
print("MID-EPISODE", flush=True)
time.sleep(60)
"""


def test_sigkill_mid_episode_loses_only_that_episode(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path)], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        line = proc.stdout.readline()
        assert line.strip() == b"MID-EPISODE", proc.stderr.read().decode()[-2000:]
    finally:
        proc.kill()  # SIGKILL: no atexit, no close, no flush
        proc.wait(10)
    run = tmp_path / "killed"
    assert not (run / "metadata.yaml").exists()
    eps, rep = read_episodes(run, include_incomplete=True)
    assert [(e.index, e.complete) for e in eps] == [(0, True), (1, True), (2, False)]
    assert all(e.seen == e.expected == 22 for e in eps[:2])
    assert eps[2].problem.startswith("no END") and 0 < eps[2].seen < 21
    assert not rep.finished and rep.episodes_incomplete == 1
    # rewritten as a finished log, the standard tools open what survived
    fixed, _ = recover_log(run)
    with AnyReader([fixed]) as ar:
        assert sum(c.msgcount for c in ar.connections) == rep.messages
    assert read_episodes(fixed)[1].episodes_complete == 2


def _layout(path):
    """Offsets of the skyloop.episode metadata records and of the chunks."""
    data = path.read_bytes()
    metas, chunks, pos = [], [], 0
    while (pos := data.find(b"skyloop.episode", pos + 1)) > 0:
        metas.append(pos - 13)  # opcode, length, string length
    for op, body, stop in records(data, len(MAGIC), len(data) - len(MAGIC)):
        if op == CHUNK:
            chunks.append((body - 9, stop))
    return data, metas, chunks


def test_truncated_file_reads_up_to_the_damage(tmp_path):
    src = make_run(tmp_path) / "run_0.mcap"
    data, metas, _ = _layout(src)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: metas[2] - 100])  # inside the last episode's final chunk
    eps, rep = read_episodes(cut, include_incomplete=True)
    assert [(e.index, e.complete) for e in eps] == [(0, True), (1, True), (2, False)]
    assert rep.truncated and not rep.finished and rep.skipped_bytes > 0
    assert rep.episodes_complete == 2 and rep.episodes_incomplete == 1
    for n in range(8, len(data), 1999):  # any cut: no exception, complete ones are exact
        cut.write_bytes(data[:n])
        eps, rep = read_episodes(cut)
        assert [e.index for e in eps] == list(range(len(eps)))
        assert all(e.seen == PER_EPISODE for e in eps)


def test_corrupt_chunk_is_skipped_and_counted(tmp_path):
    src = make_run(tmp_path) / "run_0.mcap"
    data, metas, chunks = _layout(src)
    start, stop = max(((a, b) for a, b in chunks if metas[0] < a < metas[1]),
                      key=lambda c: c[1] - c[0])  # a chunk inside episode 1
    bad = bytearray(data)
    mid = (start + stop) // 2
    bad[mid:mid + 16] = bytes(x ^ 0xFF for x in bad[mid:mid + 16])
    (tmp_path / "bad.mcap").write_bytes(bad)
    eps, rep = read_episodes(tmp_path / "bad.mcap", include_incomplete=True)
    assert [(e.index, e.complete) for e in eps] == [(0, True), (1, False), (2, True)]
    assert eps[1].problem == "damaged data inside the episode"
    assert rep.corrupt_chunks == 1 and rep.finished and rep.messages_lost > 0
    # a broken record length: the reader resynchronises on the next good record
    bad = bytearray(data)
    bad[start + 1:start + 9] = b"\xff" * 8
    (tmp_path / "len.mcap").write_bytes(bad)
    eps, rep = read_episodes(tmp_path / "len.mcap", include_incomplete=True)
    assert [(e.index, e.complete) for e in eps] == [(0, True), (1, False), (2, True)]
    assert rep.corrupt_records >= 1 and rep.skipped_bytes >= stop - start


def test_not_a_log(tmp_path):
    (tmp_path / "junk.mcap").write_bytes(os.urandom(5000))
    (tmp_path / "empty.mcap").write_bytes(b"")
    for name in ("junk.mcap", "empty.mcap"):
        eps, rep = read_episodes(tmp_path / name)
        assert eps == [] and "not an MCAP file" in rep.errors[0] and not rep.clean
    with pytest.raises(LogReadError):
        EpisodeLogReader(tmp_path / "missing.mcap")
    (tmp_path / "d").mkdir()
    with pytest.raises(LogReadError):
        EpisodeLogReader(tmp_path / "d")
    with pytest.raises(FileExistsError):  # one directory per run, never overwritten
        make_run(tmp_path, name="d")


def test_log_repair_command_makes_a_killed_log_readable(tmp_path):
    """`skyloop log repair`: a log cut where its writer died (no summary, no footer)
    becomes a finished file the indexed mcap reader opens, with every whole episode."""
    run = make_run(tmp_path, episodes=3, compression="zstd")
    src = next(run.glob("*.mcap"))
    data = src.read_bytes()
    cut = tmp_path / "killed" / "killed_0.mcap"
    cut.parent.mkdir()
    cut.write_bytes(data[: int(len(data) * 0.8)])
    with open(cut, "rb") as f, pytest.raises(Exception):  # noqa: B017 - any mcap error
        list(make_reader(f).iter_messages())
    out = subprocess.run([sys.executable, "-m", "skyloop", "log", "repair", str(cut),
                          "--out", str(tmp_path / "fixed")], capture_output=True, text=True,
                         cwd=REPO, timeout=120)
    assert out.returncode == 0, out.stderr
    fixed = next((tmp_path / "fixed").glob("*/*.mcap"))
    with open(fixed, "rb") as f:
        assert sum(1 for _ in make_reader(f).iter_messages()) > 0
    complete = read_episodes(fixed)[1].episodes_complete
    assert complete >= 1 and f": {complete} complete, " in out.stdout, out.stdout  # as it says
    missing = subprocess.run([sys.executable, "-m", "skyloop", "log", "repair",
                              str(tmp_path / "nope.mcap")], capture_output=True, text=True,
                             cwd=REPO, timeout=120)
    assert missing.returncode == 2 and "no such log file" in missing.stderr
