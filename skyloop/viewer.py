"""See a run in 3D with Rerun: live (``skyloop up --viz``, ``skyloop viz``) or from a log
(``skyloop view LOG``).

One :class:`RunView` turns the bus's messages into Rerun entities, whatever feeds them:

- ``world/terrain``, ``world/obstacles`` (static meshes, rebuilt from the scenario that the
  episode START names: worlds are deterministic from it), ``world/aircraft`` (boxes at
  the step's sim time), ``world/goal`` and ``world/start``;
- ``world/vehicle`` (its pose from ``truth``, else ``odom``) holding ``body``, ``lidar``
  (the scan in the sensor frame, coloured by range) and ``faces`` (the truncated
  icosahedron of the observation, each face coloured by its value);
  ``world/trail`` (the episode's path), ``world/cmd`` (the commanded velocity, world
  frame, drawn from the vehicle);
- ``plots/altitude``, ``plots/speed``, ``plots/distance_to_goal``, ``plots/reward`` (the
  eq. 3.5 base reward of each step, from the observation's h, g, the altitude and the
  progress to the goal; the collision reward on a collision), ``events`` (episode
  starts and ends, the vehicle's status texts).

Timelines: ``step`` (control steps over the run, from the step clock) and ``sim_time``
(the messages' header stamps: the stack time, monotonic over the run).

Targets (``--viz``): ``spawn`` (the native viewer; needs a display), ``web`` (the web
viewer served on localhost: open the printed address; for a headless machine), and
``save:PATH.rrd`` (a recording for ``rerun PATH.rrd`` later). The first scan is drawn,
then one every ``scan_every`` steps (default 5): a VLP-16 scan is ~20k points, every one
of them would make a recording of a few episodes hundreds of MB; while the live view is
behind (over 64 messages queued) one every 10 x ``scan_every`` steps.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("skyloop.viz")

TARGETS = "spawn, web or save:PATH.rrd"
#: the topics a view draws (bus.keys names)
VIEW_TOPICS = ("clock", "truth", "odom", "lidar/points", "observation", "cmd_vel",
               "episode", "status")


@dataclass(frozen=True)
class Target:
    """Where the view goes: ``kind`` is spawn, web or save (with ``path``)."""

    kind: str
    path: Path | None = None


def parse_target(text: str, flag: str = "--viz") -> Target:
    """``spawn`` | ``web`` | ``save:PATH.rrd`` -> :class:`Target`; ValueError naming
    ``flag`` otherwise."""
    if text in ("spawn", "web"):
        return Target(text)
    if text.startswith("save:") and text[5:]:
        path = Path(text[5:])
        if path.suffix != ".rrd":
            raise ValueError(f"{flag} {text}: the recording must be a .rrd file")
        return Target("save", path)
    raise ValueError(f"{flag} {text!r}: must be {TARGETS}")


def open_recording(target: Target, *, web_port: int = 9090, grpc_port: int = 9876,
                   recording_name: str = "skyloop") -> tuple[Any, str | None]:
    """A Rerun recording stream sending to ``target``; for ``web`` also the address to
    open (the gRPC server buffers what is logged before a browser connects)."""
    import os

    import rerun as rr

    if target.kind == "spawn" and not (os.environ.get("DISPLAY")
                                       or os.environ.get("WAYLAND_DISPLAY")):
        raise ValueError("--viz spawn: no display here (DISPLAY unset); use --viz web or "
                         "--viz save:PATH.rrd")
    rec = rr.RecordingStream("skyloop")
    rec.send_recording_name(recording_name)
    if target.kind == "save":
        assert target.path is not None
        target.path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(str(target.path))
        return rec, None
    if target.kind == "spawn":
        rec.spawn()
        return rec, None
    uri = rec.serve_grpc(grpc_port=grpc_port)
    rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=uri)
    from urllib.parse import quote

    return rec, f"http://127.0.0.1:{web_port}/?url={quote(uri, safe='')}"


def blueprint(extent: tuple[float, float, float, float] | None = None) -> Any:
    """The layout: the 3D world large on the left (seen from the south-west, above the
    terrain of ``extent`` = xmin, xmax, ymin, ymax), the time series and the events on
    the right."""
    import rerun.blueprint as rrb

    eye = None
    if extent is not None:
        x0, x1, y0, y1 = extent
        cx, cy, size = (x0 + x1) / 2, (y0 + y1) / 2, max(x1 - x0, y1 - y0)
        eye = rrb.EyeControls3D(position=[cx - 0.55 * size, cy - 0.75 * size, 0.6 * size],
                                look_target=[cx, cy, 0.0], eye_up=[0, 0, 1])
    plots = [rrb.TimeSeriesView(origin=f"/plots/{n}", name=n.replace("_", " "))
             for n in ("altitude", "speed", "distance_to_goal", "reward")]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/world", name="world", eye_controls=eye),
            rrb.Vertical(*plots, rrb.TextLogView(origin="/events", name="events")),
            column_shares=[3, 1]),
        rrb.TimePanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"), collapse_panels=True)


# ------------------------------------------------------------------ pure helpers
def range_colors(points: np.ndarray, max_range: float = 30.0) -> np.ndarray:
    """(N, 3) points in the sensor frame -> (N, 3) uint8: near red, far blue (by range)."""
    t = np.clip(np.linalg.norm(points, axis=1) / max_range, 0.0, 1.0)
    return np.stack([255 * (1 - t), 80 + 100 * np.sin(np.pi * t), 255 * t], 1).astype(np.uint8)


def rgba8(colours: np.ndarray) -> np.ndarray:
    """Float RGB(A) in [0, 1] (``bus.ros.view``'s colours) -> uint8 for Rerun."""
    return np.round(np.clip(np.asarray(colours, float), 0.0, 1.0) * 255).astype(np.uint8)


# ------------------------------------------------------------------ the view
@dataclass
class _Episode:
    goal: np.ndarray | None = None
    trail: list[np.ndarray] = field(default_factory=list)
    distance: float | None = None


class RunView:
    """Messages of one vehicle -> Rerun entities (see the module docstring).
    ``handle(name, msg)`` takes a decoded message of bus topic ``name``."""

    def __init__(self, rec: Any, *, scan_every: int = 5) -> None:
        import rerun as rr

        from bus.ros.scene import SitlScene
        from bus.ros.view import fan_triangles
        from policy.algorithms.rewards import RewardConfig

        self.rr, self.rec, self.scan_every = rr, rec, max(1, int(scan_every))
        self.step = 0
        self.sim_time = 0.0
        self.scenario: str | None = None
        self.scene = SitlScene()  # the geometry the log's 3D view shows too
        self.aircraft: Any = None  # t -> (K, 8) boxes of the world's aircraft, or None
        self.ep = _Episode()
        self.pose: tuple[np.ndarray, np.ndarray] | None = None  # position, quaternion xyzw
        self.reward_config = RewardConfig()
        self.ico_radius: float | None = None
        self._ico_verts, ico_faces = self.scene.icosahedron()  # circumradius 1
        self._ico_tris, self._ico_owner = fan_triangles(ico_faces)
        self._ico_edges = np.array(sorted({(min(a, b), max(a, b)) for f in ico_faces
                                           for a, b in zip(f, [*f[1:], f[0]], strict=True)}))
        self.counts = {"scans_drawn": 0, "messages": 0}
        self._scan_step: int | None = None  # the step of the last scan drawn
        rec.send_blueprint(blueprint())
        self._draw_vehicle()

    # -- time
    def _time(self, stamp: Any | None = None) -> None:
        if stamp is not None:
            self.sim_time = stamp.sec + stamp.nanosec * 1e-9
        self.rec.set_time("step", sequence=self.step)
        self.rec.set_time("sim_time", duration=self.sim_time)

    def handle(self, name: str, msg: Any) -> None:
        """Draw one message (unknown topics are ignored)."""
        self.counts["messages"] += 1
        if name == "clock":
            self.step += 1
            self.sim_time = msg.sim_time.sec + msg.sim_time.nanosec * 1e-9
            self._time()
        elif name == "episode":
            self._episode(msg)
        elif name == "truth" or (name == "odom" and self.pose is None):
            self._pose(msg)
        elif name == "lidar/points":
            self._scan(msg)
        elif name == "observation":
            self._observation(msg)
        elif name == "cmd_vel":
            self._command(msg)
        elif name == "status":
            for text in msg.event_texts:
                self._time(msg.header.stamp)
                self.rec.log("events", self.rr.TextLog(str(text), level="INFO"))

    # -- the world
    def warm(self, scenario: str) -> None:
        """Build the world of ``scenario`` ahead of its first episode (a family or a
        mixture: its template, not drawn, which warms the compiled kernels)."""
        from sitl.world.families import WorldSource

        source = WorldSource.parse(scenario)
        if source.fixed:
            self._world(scenario)
        else:
            self.scene.world(source.template())

    def _world(self, scenario: str) -> None:
        """The static world of ``scenario`` (``bus.ros.scene.SitlScene``: the terrain
        decimated, the solids by kind) in ``bus.ros.view``'s colours."""
        from bus.ros import view as ros_view

        rr = self.rr
        geo = self.scene.world(scenario)
        self.aircraft = self.scene.aircraft(scenario)
        self.scenario = scenario
        v = geo.terrain.vertices
        self.rec.send_blueprint(blueprint((v[:, 0].min(), v[:, 0].max(),
                                           v[:, 1].min(), v[:, 1].max())))
        self.rec.log("world/terrain", rr.Mesh3D(
            vertex_positions=v, triangle_indices=geo.terrain.triangles,
            vertex_colors=rgba8(ros_view.terrain_colours(v[:, 2]))), static=True)
        solids = [(mesh, colour) for mesh, colour in ((geo.buildings, ros_view.BUILDING),
                                                     (geo.trunks, ros_view.TRUNK),
                                                     (geo.crowns, ros_view.CROWN))
                  if len(mesh.triangles)]
        if solids:
            mesh = ros_view.Mesh.merge([(m.vertices, m.triangles) for m, _ in solids])
            colours = np.vstack([np.tile(c, (len(m.vertices), 1)) for m, c in solids])
            self.rec.log("world/obstacles", rr.Mesh3D(
                vertex_positions=mesh.vertices, triangle_indices=mesh.triangles,
                vertex_colors=rgba8(colours)), static=True)
        else:
            self.rec.log("world/obstacles", rr.Clear(recursive=False), static=True)

    def _draw_vehicle(self) -> None:
        rr = self.rr
        self.rec.log("world/vehicle/body", rr.Boxes3D(half_sizes=[[0.23, 0.23, 0.06]],
                                                      colors=[[40, 90, 230]],
                                                      fill_mode="solid"), static=True)

    def _episode(self, msg: Any) -> None:
        rr = self.rr
        self._time(msg.header.stamp)
        if msg.event == 0:  # START
            if msg.scenario and msg.scenario != self.scenario:
                self._world(msg.scenario)
            start = np.array([msg.start.x, msg.start.y, msg.start.z])
            goal = np.array([msg.goal.x, msg.goal.y, msg.goal.z])
            self.ep = _Episode(goal=goal, trail=[start])
            self.rec.log("world/goal", rr.Points3D([goal], radii=[0.6], colors=[[250, 200, 0]],
                                                  labels=["goal"]))
            self.rec.log("world/start", rr.Points3D([start], radii=[0.3],
                                                   colors=[[240, 240, 240]]))
            self.rec.log("events", rr.TextLog(
                f"episode {msg.episode} (seed {msg.seed}, {msg.scenario}) starts", level="INFO"))
        else:
            outcome = {1: "success", 2: "collision", 3: "timeout", 4: "aborted"}.get(
                msg.outcome, "?")
            if msg.outcome == 2:
                from policy.algorithms.rewards import collision_reward

                self.rec.log("plots/reward", rr.Scalars(collision_reward(self.reward_config)[0]))
            self.rec.log("events", rr.TextLog(
                f"episode {msg.episode}: {outcome} in {msg.steps} steps",
                level="WARN" if msg.outcome in (2, 4) else "INFO"))

    # -- the vehicle
    def _pose(self, msg: Any) -> None:
        from bus.messages import odometry_values

        rr = self.rr
        self._time(msg.header.stamp)
        p, v, q = odometry_values(msg)
        self.pose = (p, q)
        self.rec.log("world/vehicle", rr.Transform3D(translation=p, quaternion=rr.Quaternion(
            xyzw=q)))
        trail = self.ep.trail
        if not trail or np.linalg.norm(trail[-1] - p) > 0.05:
            trail.append(p)
            self.rec.log("world/trail", rr.LineStrips3D([np.asarray(trail)],
                                                         colors=[[40, 90, 230]], radii=[-2.0]))
        self.rec.log("plots/altitude", rr.Scalars(float(p[2])))
        self.rec.log("plots/speed", rr.Scalars(float(np.linalg.norm(v))))
        if self.ep.goal is not None:
            d = float(np.linalg.norm(self.ep.goal - p))
            self.rec.log("plots/distance_to_goal", rr.Scalars(d))
        if self.aircraft is not None:
            b = self.aircraft(self.sim_time)
            yaw = np.arctan2(b[:, 7], b[:, 6])
            self.rec.log("world/aircraft", rr.Boxes3D(
                centers=b[:, :3], half_sizes=b[:, 3:6], fill_mode="solid",
                colors=[[200, 60, 200]],
                rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=float(a))
                                      for a in yaw]))

    def wants_scan(self, behind: bool = False) -> bool:
        """Whether a scan at this step is drawn: the first one always, then one every
        ``scan_every`` steps (every 10 x ``scan_every`` while a live feed is behind)."""
        gap = self.scan_every * (10 if behind else 1)
        return self._scan_step is None or self.step - self._scan_step >= gap

    def _scan(self, msg: Any) -> None:
        if not self.wants_scan():
            return
        from bus.messages import points_from_pointcloud

        self._time(msg.header.stamp)
        pts = points_from_pointcloud(msg)
        pts = pts[np.isfinite(pts).all(axis=1)]
        # radii < 0: in UI points, so that the scan shows from afar
        self.rec.log("world/vehicle/lidar", self.rr.Points3D(pts, colors=range_colors(pts),
                                                             radii=[-1.5]))
        self.counts["scans_drawn"] += 1
        self._scan_step = self.step

    def _observation(self, msg: Any) -> None:
        from bus.messages import observation_scaling
        from bus.ros import view as ros_view
        from perception.observation import config_from_scaling, goal_terms
        from policy.algorithms.rewards import base_reward

        rr = self.rr
        self._time(msg.header.stamp)
        values = np.asarray(msg.values, np.float32).reshape(msg.frames, msg.attributes)[-1]
        scaling = observation_scaling(msg)
        config = config_from_scaling(scaling) if scaling else None
        radius = config.radius if config else 4.0
        if radius != self.ico_radius:  # the solid around the vehicle, at its radius
            self.ico_radius = radius
            self.rec.log("world/vehicle/solid", rr.LineStrips3D(
                self._ico_verts[self._ico_edges] * radius, colors=[[90, 200, 120]],
                radii=[0.01]))
        # the faces with something in them, filled (unshared corners: a colour a face);
        # the free ones are the wireframe
        colours = ros_view.face_colours(values[:32])
        hit = np.flatnonzero(colours[self._ico_owner, 3] > 0.0)
        if len(hit):
            corners = self._ico_tris[hit].reshape(-1)
            self.rec.log("world/vehicle/faces", rr.Mesh3D(
                vertex_positions=self._ico_verts[corners] * radius,
                triangle_indices=np.arange(len(corners)).reshape(-1, 3),
                vertex_colors=rgba8(np.repeat(colours[self._ico_owner[hit], :3], 3, axis=0))))
        else:
            self.rec.log("world/vehicle/faces", rr.Clear(recursive=False))
        if config is None or self.pose is None or self.ep.goal is None:
            return
        z, h, g = goal_terms(values, config)
        d = float(np.linalg.norm(self.ep.goal - self.pose[0]))
        if self.ep.distance is not None:
            r, _ = base_reward(self.ep.distance, d, z, h, g, self.reward_config)
            self.rec.log("plots/reward", rr.Scalars(r))
        self.ep.distance = d

    def _command(self, msg: Any) -> None:
        from bus.messages import FRAME_BODY, yaw_of
        from sitl.episode import body_to_world

        if self.pose is None:
            return
        self._time(msg.header.stamp)
        v = np.array([msg.velocity.x, msg.velocity.y, msg.velocity.z])
        if msg.frame == FRAME_BODY:
            v = body_to_world(np.append(v, 0.0), yaw_of(self.pose[1]))[:3]
        self.rec.log("world/cmd", self.rr.Arrows3D(origins=[self.pose[0]], vectors=[v],
                                                   colors=[[250, 120, 0]]))


# ------------------------------------------------------------------ feeds
def view_messages(view: RunView, messages: Iterable[tuple[str, Any]]) -> int:
    """Feed ``(topic name, message)`` pairs to ``view``; returns how many."""
    n = 0
    for name, msg in messages:
        view.handle(name, msg)
        n += 1
    return n


def log_messages(path: str | Path, vehicle: str | None = None) -> Iterable[tuple[str, Any]]:
    """The decodable messages of a log (an .mcap file or a run directory, split runs
    file by file) that a view draws, as (topic name, message). Checks the files first:
    ValueError naming the path if there is no log there."""
    from bus.log.reader import EpisodeLogReader, LogReadError, log_files

    p = Path(path)
    if not p.exists():
        raise ValueError(f"{p}: no such log")
    files = log_files(p) if p.is_dir() else [p]
    if not files:
        raise ValueError(f"{p}: no .mcap file in this directory")
    try:
        readers = [EpisodeLogReader(f) for f in files]
        first = next(iter(readers[0].messages()), None)
    except LogReadError as err:
        raise ValueError(f"{p}: {err}") from None
    if first is None:
        raise ValueError(f"{p}: no readable message (not an MCAP log, or empty)")

    def messages() -> Iterable[tuple[str, Any]]:
        for reader in readers:
            for m in reader.messages():
                if m.name in VIEW_TOPICS and (vehicle is None or m.vehicle == vehicle):
                    try:
                        yield m.name, m.decode()
                    except Exception:  # noqa: BLE001 - a damaged message is skipped
                        continue

    return messages()


class LiveFeed:
    """Bus subscriptions of one vehicle feeding a :class:`RunView` from one thread.
    Zenoh callbacks only enqueue (bounded; a full queue is a counted drop); the scan is
    kept as raw bytes, newest only, and decoded when drawn."""

    def __init__(self, bus: Any, vehicle: str, view: RunView, maxsize: int = 2048) -> None:
        import zenoh

        from bus import keys

        self.view = view
        self._q: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=maxsize)
        self.dropped = 0
        self._subs = [bus.subscribe(t, vehicle, lambda msg, t=t: self._put(t, msg))
                      for t in VIEW_TOPICS if t != "lidar/points"]
        self._scan_sub = bus.session.declare_subscriber(
            keys.key(vehicle, keys.LIDAR_POINTS),
            lambda s: self._put("lidar/points", s.payload.to_bytes()))
        self._zenoh = zenoh
        self._stop = threading.Event()
        self._drain_until = 0.0
        self._thread = threading.Thread(target=self._run, name="skyloop-viz", daemon=True)
        self._thread.start()

    def _put(self, name: str, msg: Any) -> None:
        try:
            self._q.put_nowait((name, msg))
        except queue.Full:
            self.dropped += 1

    def _run(self) -> None:
        from bus.keys import msgtype
        from bus.messages import decode

        while not (self._stop.is_set()
                   and (self._q.empty() or time.monotonic() > self._drain_until)):
            try:
                name, msg = self._q.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                if name == "lidar/points":
                    if not self.view.wants_scan(behind=self._q.qsize() > 64):
                        continue  # not drawn at this step (fewer while the view is behind)
                    msg = decode(msgtype("lidar/points"), msg)
                self.view.handle(name, msg)
            except Exception:  # noqa: BLE001 - one bad message must not stop the view
                log.exception("viz: drawing %s failed", name)

    def close(self, drain_s: float = 2.0) -> None:
        """Undeclare every subscriber, draw what is queued (for at most ``drain_s``; the
        rest counts as dropped), then stop the drawing thread."""
        for s in self._subs:
            s.close()
        self._scan_sub.undeclare()
        self._drain_until = time.monotonic() + drain_s
        self._stop.set()
        self._thread.join(drain_s + 3.0)
        self.dropped += self._q.qsize()


def run_live(vehicle: str, target: Target, stop: threading.Event, *,
             session_config: Any = None, scan_every: int = 5, web_port: int = 9090,
             grpc_port: int = 9876, scenario: str | None = None) -> dict[str, int]:
    """``skyloop viz``: draw ``vehicle``'s run from the bus until ``stop``; declares the
    readiness token ``viz`` once subscribed, after building ``scenario``'s world (a
    world built at the first episode's start would hold the drawing up for seconds on
    a loaded machine, while a short run flies on). Returns counters."""
    from bus.node import Bus

    rec, url = open_recording(target, web_port=web_port, grpc_port=grpc_port,
                              recording_name=f"skyloop {vehicle} live")
    view = RunView(rec, scan_every=scan_every)
    if scenario:
        view.warm(scenario)
    bus = Bus.open(session_config)
    try:
        feed = LiveFeed(bus, vehicle, view)
        bus.declare_ready(vehicle, "viz")
        print(f"viz: drawing {vehicle} to {url or target.path or 'the native viewer'}",
              flush=True)
        try:
            while not stop.is_set():  # not stop.wait(): a signal handler may set it
                time.sleep(0.1)  # in this thread (Event.set in Event.wait: deadlock)
        except KeyboardInterrupt:
            pass
        feed.close()
    finally:
        bus.close()
    rec.flush()
    if target.kind == "save":
        rec.disconnect()
    return {**view.counts, "dropped": feed.dropped}


def view_log(path: str | Path, target: Target, *, vehicle: str | None = None,
             scan_every: int = 5, web_port: int = 9090, grpc_port: int = 9876,
             wait: bool = True) -> dict[str, int]:
    """``skyloop view LOG``: draw a recorded run; with ``web`` (and ``wait``) serve it
    until Ctrl-C. Returns counters."""
    t0 = time.monotonic()
    messages = log_messages(path, vehicle)  # a bad path fails before any viewer starts
    rec, url = open_recording(target, web_port=web_port, grpc_port=grpc_port,
                              recording_name=f"skyloop {Path(path).name}")
    view = RunView(rec, scan_every=scan_every)
    n = view_messages(view, messages)
    rec.flush()
    print(f"view: {n} messages, {view.counts['scans_drawn']} scans drawn in "
          f"{time.monotonic() - t0:.1f} s", flush=True)
    if target.kind == "save":
        rec.disconnect()
        print(f"saved {target.path} (open it with: rerun {target.path})", flush=True)
    elif target.kind == "web":
        print(f"open {url} (Ctrl-C to stop)", flush=True)
        if wait:
            try:
                while True:
                    time.sleep(1.0)
            except KeyboardInterrupt:
                pass
    return view.counts
