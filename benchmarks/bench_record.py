"""Recorder benchmark: sustained rate at full VLP-16 scans, with drops counted.

A publisher process sends episodes of full 28,800-point scans (345 KB each, BLOCK
congestion control) at a fixed rate for a fixed time; a recorder in this process writes
them to an MCAP log. Reports scans/s written, MB/s, and ``recorder_dropped`` (recorder
queue overflows; the goal is zero) at 100 scans/s (10x a VLP-16), and the same at the
publisher's full speed (``_max``) where drops show the recorder's ceiling.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time

import numpy as np

from bus import keys
from bus import messages as m
from bus.log import EpisodeLogWriter
from bus.node import Bus
from bus.record import Recorder
from bus.session import SessionConfig, open_session
from skyloop.launcher import free_port

SCAN = np.random.default_rng(0).normal(scale=10, size=(28_800, 3)).astype(np.float32)


def publish(hub: str, duration: float, rate: float) -> None:
    """The publisher process: episodes of 100 scans, ``rate`` scans/s (0: flat out)."""
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
                pubs[keys.LIDAR_POINTS].put(m.pointcloud(SCAN, 0.1 * step))
                sent += 1
            pubs[keys.EPISODE].put(m.episode_end(episode, "timeout", 100, 10.0))
            episode += 1
        print(sent, episode, flush=True)
    finally:
        bus.close()


def measure(duration: float, rate: float) -> tuple[float, int, int]:
    """(scans/s written, dropped, lost) for one publisher run."""
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    with tempfile.TemporaryDirectory() as tmp:
        rec_session = open_session(cfg)
        recorder = Recorder(rec_session, EpisodeLogWriter(tmp, "bench"))
        try:
            t0 = time.perf_counter()
            out = subprocess.run([sys.executable, "-m", "benchmarks.bench_record", cfg.hub,
                                  str(duration), str(rate)], capture_output=True, text=True,
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
    return {"recorder_scans_per_s": rate, "recorder_mb_per_s": rate * size_mb,
            "recorder_dropped": dropped, "recorder_lost": lost,
            "recorder_scans_per_s_max": peak, "recorder_dropped_max": peak_dropped}


if __name__ == "__main__":
    publish(sys.argv[1], float(sys.argv[2]), float(sys.argv[3]))
