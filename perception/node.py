"""The perception node (``skyloop perception``): scan + odometry + goal -> observation.

Inputs (one vehicle): the episode START event (the goal), the step clock (episode and
step of a stamp), the estimated odometry and the LiDAR scan. Messages of one step share
one header stamp (the simulator's stack time); the node joins them by stamp, so their
arrival order does not matter, and publishes ``observation`` (35 values, one frame,
with the episode and step) through :func:`perception.observation.observation_from_scan`,
the same function the in-process env calls. Zenoh callbacks only enqueue; one worker
thread does the work. Once subscribed, with its publisher declared and its worker
running, the node holds the readiness token ``skyloop/<vehicle>/ready/perception``
(``bus.node.Bus.declare_ready``), what ``skyloop up`` waits on; gone on :meth:`close`.

Parameters (``skyloop/<vehicle>/params``, set by a ground station through the bridge):
``SKY_ICO_RADIUS`` replaces the icosahedron radius (eq. 3.1's p_radius) from the next
observation on; an invalid value is logged and counted (``param_rejects``); the sim's
parameters are not perception's and are ignored.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
from dataclasses import replace
from typing import Any

import numpy as np

from bus import keys, params
from bus import messages as m
from bus.node import Bus
from perception.icosahedron import TruncatedIcosahedron
from perception.observation import ObservationConfig, observation_from_scan, scaling_fields

log = logging.getLogger("skyloop.perception")
_MAX_PENDING = 64  # stamps waiting for their other parts


def yaw_from_quat(x: float, y: float, z: float, w: float) -> float:
    """ENU yaw (CCW from east) of an (x, y, z, w) quaternion (ZYX)."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


class PerceptionNode:
    """Joins clock/odometry/scan by stamp and publishes observations."""

    def __init__(self, bus: Bus, vehicle: str = "uav1",
                 config: ObservationConfig | None = None, queue_size: int = 64) -> None:
        self.bus, self.vehicle = bus, vehicle
        self.config = config or ObservationConfig()
        self.ico = TruncatedIcosahedron(self.config.radius)
        self._scaling: tuple[ObservationConfig, dict] | None = None  # (config, its fields)
        self.goals: dict[int, np.ndarray] = {}
        self.pending: dict[int, dict[str, Any]] = {}
        self.published = 0
        self.param_rejects = 0
        # Bounded: step data (scans, odometry, clock) offered faster than it is reduced is
        # dropped and counted (``dropped``), not queued without end (2 GB in 8 s at ~1,400
        # scans/s, seen). Episode events and parameters, rare, get the other half of the
        # queue: a full queue of step data still takes a START (a lost one would lose its
        # episode's goal) or a parameter; only a flood of them is dropped and counted too
        # (``dropped_events``, also in ``dropped``), each drop logged.
        self.dropped = 0
        self.dropped_events = 0
        self.queue_size = int(queue_size)
        self._q: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=2 * self.queue_size)
        self._stop = threading.Event()
        self._count_lock = threading.Lock()
        # Warm up (numba compiles on the first call) before anyone can wait on us.
        observation_from_scan(np.ones((16, 3), np.float32), self.ico, np.zeros(3), 0.0,
                              np.zeros(3), np.ones(3), self.config)
        self.pub = bus.publisher(keys.OBSERVATION, vehicle)
        for topic in (keys.EPISODE, keys.CLOCK, keys.ODOM, keys.LIDAR_POINTS, keys.PARAMS):
            bus.subscribe(topic, vehicle, lambda msg, t=topic: self._offer(t, msg))
        self._thread = threading.Thread(target=self._run, name="perception", daemon=True)
        self._thread.start()
        # Subscribed, the publisher declared, the worker running: what ``skyloop up``
        # waits on (the readiness token ``skyloop/<vehicle>/ready/perception``).
        self.ready = bus.declare_ready(vehicle, "perception")

    def _offer(self, topic: str, msg: Any) -> None:
        """Zenoh's callback: queue the message, or count it dropped if the queue is full."""
        if self._stop.is_set():
            return  # closing: nothing will handle it
        event = topic in (keys.EPISODE, keys.PARAMS)
        if event or self._q.qsize() < self.queue_size:
            try:
                self._q.put_nowait((topic, msg))
                return
            except queue.Full:  # the events' half is full too
                pass
        with self._count_lock:  # Zenoh calls back from several threads
            self.dropped += 1
            self.dropped_events += event
            dropped = self.dropped
        if event:
            log.warning("overloaded: dropped a message on '%s' (%d episode events or "
                        "parameters so far)", topic, self.dropped_events)
        elif dropped in (1, 10, 100) or dropped % 1000 == 0:
            log.warning("overloaded: %d messages dropped so far", dropped)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                item = self._q.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                self.handle(*item)
            except Exception:  # noqa: BLE001 - one bad step must not stop the node
                log.exception("perception failed on %s", item[0])

    def handle(self, topic: str, msg: Any) -> None:
        """Take one message; publish an observation once a stamp is complete."""
        if topic == keys.PARAMS:
            self._set_param(str(msg.name), msg.value)
            return
        if topic == keys.EPISODE:
            if msg.event == m.START:
                self.goals[int(msg.episode)] = np.array([msg.goal.x, msg.goal.y, msg.goal.z])
                for old in [e for e in self.goals if e < msg.episode - 4]:
                    del self.goals[old]
            self._flush()
            return
        stamp = m.nanoseconds(msg.header.stamp) if topic != keys.CLOCK \
            else m.nanoseconds(msg.sim_time)
        self.pending.setdefault(stamp, {})[topic] = msg
        while len(self.pending) > _MAX_PENDING:
            del self.pending[min(self.pending)]
        self._flush()

    def _set_param(self, name: str, value: float) -> None:
        known = params.BY_NAME.get(name)
        if known is not None and known.applies_to != "perception":
            return  # the sim's
        try:
            radius = params.check(name, value)
        except ValueError as err:
            self.param_rejects += 1
            log.warning("parameter rejected: %s", err)
            return
        if radius != self.config.radius:
            self.config = replace(self.config, radius=radius)
            self.ico = TruncatedIcosahedron(radius)
            log.info("SKY_ICO_RADIUS = %g m", radius)

    def _flush(self) -> None:
        for stamp in sorted(self.pending):
            parts = self.pending[stamp]
            if len(parts) < 3:
                continue
            clock = parts[keys.CLOCK]
            goal = self.goals.get(int(clock.episode))
            if goal is None:
                continue
            del self.pending[stamp]
            self._observe(stamp, clock, parts[keys.ODOM], parts[keys.LIDAR_POINTS], goal)

    def _observe(self, stamp: int, clock: Any, odom: Any, scan: Any, goal: np.ndarray) -> None:
        position, velocity, q = m.odometry_values(odom)
        points = m.points_from_pointcloud(scan)
        obs, _, _, _ = observation_from_scan(points, self.ico, position, yaw_from_quat(*q),
                                             velocity, goal, self.config)
        if self._scaling is None or self._scaling[0] is not self.config:
            self._scaling = (self.config, scaling_fields(self.config))
        self.pub.put(m.observation(obs, stamp / 1e9, int(clock.episode), int(clock.step),
                                   scaling=self._scaling[1]))
        self.published += 1

    def close(self) -> None:
        """Stop the worker (what is still queued is dropped); close the bus after this,
        so that the worker never publishes on a closed publisher. The readiness token
        goes first: a node that is stopping is not ready."""
        self.ready.close()
        self._stop.set()
        self._thread.join(timeout=5.0)
