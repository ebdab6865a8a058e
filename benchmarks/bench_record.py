"""Recorder benchmark: sustained rate with drops counted, and the log's size per episode.

A publisher process sends episodes of 100 scans (BLOCK congestion control) at a fixed
rate for a fixed time; a recorder in this process writes them to an MCAP log. Reports
scans/s written over the whole wall time (publisher start-up included), MB/s (of
messages, before any compression), and ``recorder_dropped`` (recorder queue overflows;
the goal is zero) at 100 scans/s (10x a VLP-16), and the same at the publisher's full
speed (``_max``) where drops show the recorder's ceiling; ``recorder_lost`` counts what
was sent but neither written nor counted (the goal is zero too).

- ``recorder_*`` (no suffix, ``_max``): full 28,800-point scans of random normal points
  (345 KB, x, y, z only), uncompressed log: the worst case for size and for the
  validation, and random floats do not compress.
- ``recorder_*_zstd`` (``_max_zstd``): the default log (zstd chunks) of real scans: the
  100 scans of the first episode below, x, y, z, intensity, ring as the sim node
  publishes them (``bus.messages.pointcloud`` with ``elevation_rings``); quick: 1.5 s
  runs instead of 3, so start-up weighs more in scans/s. Full mode only:
  ``recorder_*_max_real_none``, the same real scans flat out into an uncompressed log,
  the baseline of ``_max_zstd``.
- ``log_mb_per_episode_<none|zstd|lz4>``: MB on disk per episode of 100 control steps
  written with ``EpisodeLogWriter`` in this process: what the sim node publishes each
  step (clock, odometry, truth, the scan) and the setpoint, START and END. The episodes
  are flown in ``sitl.episode.EpisodeSim`` (valley, the stack's 4.5 m LiDAR range, range
  noise on) by a controller that turns to the goal and flies at 1 m/s, from seeds 0, 1,
  ... skipping seeds whose flight hits terrain before 100 steps (2 episodes quick, 5
  full). A recorded stack log also holds the observations and the 3D view's topics
  (TF, markers, path: a few percent of its size), which are left out here.
  ``log_points_per_scan``: mean returns of those scans; ``log_zstd_ratio``: zstd size /
  uncompressed size; ``log_write_ms_per_scan_<compression>``: CPU time of this process
  per step to write them (median of 3 passes). zstd is written at ``bus.log.writer.ZSTD_LEVEL``
  (``log_zstd_level``); ``log_*_zstd_level3`` are the same at zstandard's default level 3
  (the level before 2026-12-03), measured in the same run.
"""

from __future__ import annotations

import math
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bus import keys
from bus import messages as m
from bus.log import writer as log_module
from bus.log.record import Recorder
from bus.log.writer import EpisodeLogWriter
from bus.node import Bus
from bus.session import SessionConfig, open_session
from skyloop.launcher import free_port

SCAN = np.random.default_rng(0).normal(scale=10, size=(28_800, 3)).astype(np.float32)
STEPS = 100  # control steps (scans) per episode
COMPRESSIONS = ("none", "zstd", "lz4")


def fly_episodes(n: int, scenario: str = "valley") -> list[dict]:
    """``n`` real episodes of ``STEPS`` control steps (see the module docstring): each a
    dict of seed, start, goal and ``steps``, a list of (topic, msgtype, CDR bytes) in
    the order the sim node and the policy publish them."""
    from sitl.episode import EpisodeConfig, EpisodeSim
    from sitl.node.util import quat_from_matrix, quat_from_yaw

    sim = EpisodeSim(EpisodeConfig(scenario=scenario))
    lidar = sim.lidar.config
    out: list[dict] = []
    seed = 0
    while len(out) < n:
        sim.reset(np.random.default_rng(seed))
        steps: list[tuple[str, str, bytes]] = []
        for step in range(STEPS):
            est, truth, stamp = sim.vehicle.estimate, sim.vehicle.truth, sim.time
            points = sim.scan()
            for topic, msg in (
                    (keys.CLOCK, m.step_clock(step, stamp, len(out))),
                    (keys.ODOM, m.odometry(est.position, est.velocity,
                                           quat_from_yaw(est.yaw), stamp)),
                    (keys.TRUTH, m.odometry(truth.position, truth.velocity,
                                            quat_from_matrix(truth.rotation), stamp)),
                    (keys.LIDAR_POINTS, m.pointcloud(points, stamp, rings=m.elevation_rings(
                        points, lidar.min_elevation_deg, lidar.max_elevation_deg,
                        lidar.channels)))):
                steps.append((topic, msg.__msgtype__, m.encode(msg)))
            to_goal = sim.goal - truth.position
            turn = (math.atan2(to_goal[1], to_goal[0]) - est.yaw + math.pi) % (2 * math.pi) \
                - math.pi
            command = np.array([1.0 if abs(turn) < 0.5 else 0.2, 0.0, 0.0,
                                float(np.clip(2 * turn, -1.0, 1.0))])
            setpoint = m.velocity_setpoint(command[:3], command[3], stamp, body=True)
            steps.append((keys.CMD_VEL, setpoint.__msgtype__, m.encode(setpoint)))
            if sim.step_body(command):
                break
        else:
            out.append({"seed": seed, "start": sim.start, "goal": sim.goal, "steps": steps})
        seed += 1
    return out


def write_log(out_dir: str, episodes: list[dict], compression: str) -> tuple[int, float]:
    """(bytes on disk, CPU seconds) of ``episodes`` written to one log."""
    t_cpu = time.process_time()
    with EpisodeLogWriter(out_dir, f"size-{compression}", compression=compression) as w:
        t = 1_000_000_000
        for i, ep in enumerate(episodes):
            w.write_msg("uav1", keys.EPISODE, m.episode_start(
                i, ep["seed"], ep["start"], ep["goal"], 0.0, "valley"), t)
            for topic, kind, data in ep["steps"]:
                t += 1_000_000
                w.write(keys.ros_topic("uav1", topic), kind, data, t)
            w.write_msg("uav1", keys.EPISODE, m.episode_end(i, "timeout", STEPS, 0.1 * STEPS), t)
    cpu = time.process_time() - t_cpu
    return sum(p.stat().st_size for p in w.paths), cpu


def log_sizes(episodes: list[dict]) -> dict:
    """The ``log_*`` rows (module docstring)."""
    clouds = [data for ep in episodes for topic, _, data in ep["steps"]
              if topic == keys.LIDAR_POINTS]
    scans = len(clouds)
    points = [m.decode(m.POINTCLOUD2, c).width for c in clouds]
    rows: dict = {"log_points_per_scan": float(np.mean(points))}
    with tempfile.TemporaryDirectory() as tmp:
        for compression in COMPRESSIONS:
            sizes, cpus = [], []
            for k in range(3):
                size, cpu = write_log(f"{tmp}/{k}", episodes, compression)
                sizes.append(size)
                cpus.append(cpu)
            rows[f"log_mb_per_episode_{compression}"] = sizes[0] / 1e6 / len(episodes)
            rows[f"log_write_ms_per_scan_{compression}"] = statistics.median(cpus) * 1e3 / scans
        # zstd at zstandard's default level 3 (the level before 2026-12-03), as a peer
        sizes, cpus = [], []
        level, log_module.ZSTD_LEVEL = log_module.ZSTD_LEVEL, 3
        try:
            for k in range(3):
                size, cpu = write_log(f"{tmp}/level3-{k}", episodes, "zstd")
                sizes.append(size)
                cpus.append(cpu)
        finally:
            log_module.ZSTD_LEVEL = level
        rows["log_mb_per_episode_zstd_level3"] = sizes[0] / 1e6 / len(episodes)
        rows["log_write_ms_per_scan_zstd_level3"] = statistics.median(cpus) * 1e3 / scans
    rows["log_zstd_level"] = log_module.ZSTD_LEVEL
    rows["log_zstd_ratio"] = rows["log_mb_per_episode_zstd"] / rows["log_mb_per_episode_none"]
    return rows


def save_scans(path: Path, episode: dict) -> float:
    """The episode's encoded clouds into ``path`` (for the publisher); mean MB a scan."""
    clouds = [np.frombuffer(data, np.uint8) for topic, _, data in episode["steps"]
              if topic == keys.LIDAR_POINTS]
    np.savez(path, *clouds)
    return sum(c.size for c in clouds) / len(clouds) / 1e6


def load_scans(path: str) -> list[bytes]:
    with np.load(path) as f:
        return [f[f"arr_{i}"].tobytes() for i in range(len(f.files))]


def publish(hub: str, duration: float, rate: float, scans_path: str | None = None) -> None:
    """The publisher process: episodes of 100 scans, ``rate`` scans/s (0: flat out); the
    random scan, or the encoded scans saved in ``scans_path`` (sent as they are)."""
    real = load_scans(scans_path) if scans_path else None
    bus = Bus.open(SessionConfig(hub=hub))
    try:
        pubs = {t: bus.publisher(t, "uav1") for t in (keys.EPISODE, keys.LIDAR_POINTS)}
        for pub in pubs.values():
            pub.wait_matched(10.0)
        sent, episode, t0 = 0, 0, time.perf_counter()
        while time.perf_counter() - t0 < duration:
            pubs[keys.EPISODE].put(m.episode_start(episode, episode, (0, 0, 0), (1, 0, 0),
                                                   0.0, "bench"))
            for step in range(100):
                if rate:
                    delay = t0 + sent / rate - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                if real is None:
                    pubs[keys.LIDAR_POINTS].put(m.pointcloud(SCAN, 0.1 * step))
                else:
                    pubs[keys.LIDAR_POINTS].put_bytes(real[step % len(real)])
                sent += 1
            pubs[keys.EPISODE].put(m.episode_end(episode, "timeout", 100, 10.0))
            episode += 1
        print(sent, episode, flush=True)
    finally:
        bus.close()


def measure(duration: float, rate: float, compression: str = "none",
            scans_path: Path | None = None) -> tuple[float, int, int]:
    """(scans/s written, dropped, lost) for one publisher run (``scans_path``: the real
    scans :func:`save_scans` wrote, else the random one)."""
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    with tempfile.TemporaryDirectory() as tmp:
        rec_session = open_session(cfg)
        recorder = Recorder(rec_session, EpisodeLogWriter(tmp, "bench", compression=compression))
        try:
            t0 = time.perf_counter()
            extra = [str(scans_path)] if scans_path else []
            out = subprocess.run([sys.executable, "-m", "benchmarks.bench_record", cfg.hub,
                                  str(duration), str(rate), *extra], capture_output=True,
                                 text=True,
                                 timeout=duration + 60, check=True)
            scans, episodes = (int(x) for x in out.stdout.split())
            recorder.wait_written(scans + 2 * episodes - recorder.counters()["dropped"], 30.0)
            wall = time.perf_counter() - t0
            counters = recorder.stop()
        finally:
            recorder.stop()
            rec_session.close()
    written = counters["written"] - 2 * episodes
    return written / wall, counters["dropped"], scans + 2 * episodes - counters["written"] \
        - counters["dropped"]


def run(quick: bool) -> dict:
    duration = 3.0 if quick else 10.0
    size_mb = len(m.encode(m.pointcloud(SCAN, 0.0))) / 1e6
    rate, dropped, lost = measure(duration, 100.0)
    peak, peak_dropped, _ = measure(duration, 0.0)
    rows = {"recorder_scans_per_s": rate, "recorder_mb_per_s": rate * size_mb,
            "recorder_dropped": dropped, "recorder_lost": lost,
            "recorder_scans_per_s_max": peak, "recorder_dropped_max": peak_dropped}
    episodes = fly_episodes(2 if quick else 5)
    rows.update(log_sizes(episodes))
    real_duration = 1.5 if quick else duration
    with tempfile.TemporaryDirectory() as tmp:
        scans = Path(tmp) / "scans.npz"
        real_mb = save_scans(scans, episodes[0])
        rate, dropped, lost = measure(real_duration, 100.0, "zstd", scans)
        peak, peak_dropped, peak_lost = measure(real_duration, 0.0, "zstd", scans)
        rows.update({"recorder_scans_per_s_zstd": rate,
                     "recorder_mb_per_s_zstd": rate * real_mb,
                     "recorder_dropped_zstd": dropped, "recorder_lost_zstd": lost,
                     "recorder_scans_per_s_max_zstd": peak,
                     "recorder_dropped_max_zstd": peak_dropped,
                     "recorder_lost_max_zstd": peak_lost})
        if not quick:  # the same scans uncompressed: what zstd costs the recorder
            peak, peak_dropped, _ = measure(real_duration, 0.0, "none", scans)
            rows.update({"recorder_scans_per_s_max_real_none": peak,
                         "recorder_dropped_max_real_none": peak_dropped})
    return rows


if __name__ == "__main__":
    publish(sys.argv[1], float(sys.argv[2]), float(sys.argv[3]),
            sys.argv[4] if len(sys.argv) > 4 else None)
