"""Logs that show the flight in 3D by ROS 2 conventions (issue 12 section 1): the VLP-16
point-cloud layout, the derived log topics (TF, clock, world, goal, path, icosahedron),
a short real run read back with rosbags, and the generated ``skyloop_msgs`` package."""

from __future__ import annotations

import numpy as np
import pytest

from bus import messages as m


# ------------------------------------------------------------------ the point cloud
def test_cloud_has_the_vlp16_fields_and_perception_still_reads_xyz():
    pts = np.random.default_rng(1).normal(scale=5, size=(500, 3)).astype(np.float32)
    rings = m.elevation_rings(pts, -15.0, 15.0, 16)
    back = m.decode(m.POINTCLOUD2, m.encode(m.pointcloud(pts, 2.5, rings=rings)))
    layout = [(f.name, f.offset, f.datatype, f.count) for f in back.fields]
    # velodyne_pointcloud's ROS 2 XYZIR: float32 x y z intensity, uint16 ring, no padding
    assert layout == [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1),
                      ("intensity", 12, 7, 1), ("ring", 16, 4, 1)]
    assert (back.point_step, back.row_step, back.header.frame_id) == (18, 18 * 500, "lidar")
    np.testing.assert_array_equal(m.points_from_pointcloud(back), pts)
    np.testing.assert_array_equal(m.pointcloud_field(back, "ring"), rings)
    assert (m.pointcloud_field(back, "intensity") == m.LIDAR_INTENSITY).all()
    with pytest.raises(ValueError, match="no field"):
        m.pointcloud_field(back, "time")


def test_rings_are_the_lidar_channels():
    """Each return's ring recovered from its elevation is the channel of its ray (rays
    are column-major, ``channel = ray % 16``), on a full-range forest scan."""
    from sitl.lidar.scanner import Lidar, LidarConfig
    from sitl.world.world import World, load_scenario

    lidar = Lidar(World(load_scenario("forest")),
                  LidarConfig(max_range=100.0, min_range=0.0, noise_sigma=0.0))
    pose = (np.array([0.0, 0.0, 3.5]), np.eye(3))
    pts = lidar.scan(*pose, 0.0)
    rays = np.flatnonzero(lidar.ranges(*pose, 0.0) < 100.0)
    assert len(pts) == len(rays) > 10_000
    cfg = lidar.config
    rings = m.elevation_rings(pts, cfg.min_elevation_deg, cfg.max_elevation_deg, cfg.channels)
    np.testing.assert_array_equal(rings, rays % 16)


# ------------------------------------------------------------------ the skyloop_msgs package
def test_ros2_package_lists_every_msg_and_dependency(tmp_path, capsys):
    """The generated interface package: every bus/msg/*.msg copied and listed in
    rosidl_generate_interfaces, every package whose types they use (read from the type
    store's field definitions, independently of the generator) a dependency in
    package.xml and CMakeLists.txt."""
    import xml.etree.ElementTree as ET

    from bus.ros import package as ros2_pkg

    assert ros2_pkg.main(["--out", str(tmp_path)]) == 0
    assert "skyloop_msgs" in capsys.readouterr().out
    root = tmp_path / "skyloop_msgs"
    names = sorted(p.name for p in m.MSG_DIR.glob("*.msg"))
    assert names and sorted(p.name for p in (root / "msg").glob("*.msg")) == names
    for name in names:
        assert (root / "msg" / name).read_bytes() == (m.MSG_DIR / name).read_bytes()
    assert {f"skyloop_msgs/msg/{n[:-4]}" for n in names} == set(m.PROJECT_TYPES)

    def used(type_name: str) -> set[str]:
        out = set()
        for _, (kind, detail) in m.TYPESTORE.fielddefs[type_name][1]:
            sub = detail[0] if kind in (3, 4) else detail  # arrays, sequences: element
            if isinstance(sub, tuple) and sub[0] == 2:
                sub = sub[1]
            if isinstance(sub, str):
                out.add(sub.split("/")[0])
        return out

    expected = set().union(*(used(t) for t in m.PROJECT_TYPES)) - {"skyloop_msgs"}
    assert expected == {"builtin_interfaces", "geometry_msgs", "std_msgs"}

    pkg = ET.parse(root / "package.xml").getroot()
    assert pkg.get("format") == "3" and pkg.findtext("name") == "skyloop_msgs"
    assert {e.text for e in pkg.findall("depend")} == expected
    assert {e.text for e in pkg.findall("buildtool_depend")} == {
        "ament_cmake", "rosidl_default_generators"}
    assert pkg.findtext("exec_depend") == "rosidl_default_runtime"
    assert pkg.findtext("member_of_group") == "rosidl_interface_packages"
    assert pkg.find("export").findtext("build_type") == "ament_cmake"

    cmake = (root / "CMakeLists.txt").read_text()
    assert "project(skyloop_msgs)" in cmake
    block = cmake.split("rosidl_generate_interfaces(${PROJECT_NAME}", 1)[1].split(")", 1)[0]
    assert sorted(line.strip().strip('"') for line in block.splitlines()
                  if line.strip().startswith('"')) == [f"msg/{n}" for n in names]
    deps_line = next(line for line in block.splitlines() if "DEPENDENCIES" in line)
    assert set(deps_line.split()[1:]) == expected
    for dep in expected | {"ament_cmake", "rosidl_default_generators"}:
        assert f"find_package({dep} REQUIRED)" in cmake
    assert "ament_package()" in cmake


# ------------------------------------------------------------------ helpers
def frame_ids(msg, out: set[str] | None = None) -> set[str]:
    """Every frame a message names: its headers' ``frame_id`` (nested ones too: markers,
    transforms, path poses) and ``child_frame_id``; a marker's unused texture aside."""
    out = set() if out is None else out
    if not hasattr(msg, "__msgtype__"):
        return out
    if msg.__msgtype__ == "std_msgs/msg/Header":
        out.add(msg.frame_id)
        return out
    for name in msg.__dataclass_fields__:
        if name == "texture" or name.isupper():
            continue
        value = getattr(msg, name)
        if name == "child_frame_id":
            out.add(value)
        elif isinstance(value, list):
            for item in value:
                frame_ids(item, out)
        else:
            frame_ids(value, out)
    return out


def tf_tree(messages) -> dict[str, set[str]]:
    """parent -> children of every transform in ``/tf`` and ``/tf_static`` messages."""
    tree: dict[str, set[str]] = {}
    for msg in messages:
        for t in msg.transforms:
            tree.setdefault(t.header.frame_id, set()).add(t.child_frame_id)
    return tree


def reachable(tree: dict[str, set[str]], root: str = "world") -> set[str]:
    seen, todo = {root}, [root]
    while todo:
        for child in tree.get(todo.pop(), ()):
            if child not in seen:
                seen.add(child)
                todo.append(child)
    return seen


# ------------------------------------------------------------------ the recorder's view
class FakeScene:
    """A scene without the simulator: one-triangle terrain and crowns, one aircraft
    flying along x at 1 m/s, perception's icosahedron."""

    def warm(self) -> None:
        pass

    def aircraft(self, scenario):
        return lambda t: np.array([[t, 0.0, 3.0, 1.0, 0.5, 0.2, 1.0, 0.0]])

    def world(self, scenario):
        from bus.ros.view import Mesh, WorldGeometry

        tri = Mesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))
        return WorldGeometry(tri, Mesh.empty(), Mesh.empty(), tri, 0.3)

    def icosahedron(self):
        from perception.icosahedron import TruncatedIcosahedron

        ico = TruncatedIcosahedron(1.0)
        return ico.vertices, ico.faces


def test_view_writes_the_bytes_of_the_message_objects():
    """The view writes ``/tf``, the path and the icosahedron as CDR directly (issue 11,
    "Speed"): the same bytes as ``m.encode`` of the message objects, for occupied, free
    and partly occupied faces, with and without the edges, odd stamps and radii, frames
    of other lengths (CDR alignment), and paths whose poses are written once."""
    from bus.ros import view as rv

    vertices, faces = FakeScene().icosahedron()
    rng = np.random.default_rng(11)
    for trial in range(60):
        values = rng.uniform(-0.2, 1.3, 32) * (rng.uniform(size=32) < trial / 60)
        radius, stamp = float(rng.uniform(0.3, 6.0)), float(rng.uniform(0.0, 1e5))
        edges = trial % 3 == 0
        assert rv.icosahedron_cdr(vertices, faces, values, radius, stamp, edges=edges) == \
            m.encode(rv.icosahedron_markers(vertices, faces, values, radius, stamp,
                                            edges=edges))
    view = rv.RosView(None, path_every=3)
    start = m.episode_start(0, 1, (0, 0, 1), (9, 0, 1), 0.5)
    assert view.derive("uav1", "episode", start, 0)
    poses = []
    for k, frame in enumerate(["world"] * 7 + ["w", "odom_frame"] * 2):
        pos, q = rng.normal(size=3), rng.normal(size=4)
        truth = m.odometry(pos, rng.normal(size=3), q, 0.5 + 0.1 * k, frame_id=frame,
                           child_frame_id="base_link" if k % 2 else "body")
        out = dict((topic, data) for topic, _, data in view.derive("uav1", "truth", truth, 0))
        stamp = m.seconds(truth.header.stamp)
        tf = rv.transform(frame, truth.child_frame_id, stamp, pos, q)
        assert out[rv.TF] == m.encode(rv.tf_message([tf]))
        poses.append(m.PoseStamped(header=tf.header, pose=truth.pose.pose))
        if k % 3 == 0:
            assert out[rv.path_topic("uav1")] == m.encode(
                rv._Path(header=poses[-1].header, poses=list(poses)))
        else:
            assert rv.path_topic("uav1") not in out


def test_recorder_view_in_every_file_of_a_split_run(tmp_path):
    """Through a real bus into a log split every episode: each file begins with
    /tf_static and holds the world and the goal (latched, as a file is opened alone);
    TF, clock, path (every 3rd pose and at END), aircraft at episode time, the
    icosahedron only when its colours change; another vehicle's messages derive
    nothing; the bus messages are all there, counted apart from the derived ones."""
    from loopback import free_port

    from bus import keys
    from bus.log.reader import EpisodeLogReader, log_files
    from bus.log.record import Recorder
    from bus.log.writer import EpisodeLogWriter
    from bus.node import Bus
    from bus.ros.view import RosView
    from bus.session import SessionConfig, open_session

    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    bus = Bus.open(cfg)
    session = open_session(cfg)
    writer = EpisodeLogWriter(tmp_path, "split", split_episodes=1)
    recorder = Recorder(session, writer, view=RosView(FakeScene(), path_every=3))
    pts = np.array([[2.0, 0.0, 0.0], [0.0, 2.0, 0.5]], np.float32)
    try:
        pubs = {t: bus.publisher(t, "uav1") for t in keys.TOPICS}
        other = bus.publisher(keys.TRUTH, "uav2")
        for pub in (*pubs.values(), other):
            assert pub.wait_matched(10.0)
        sent = 0

        def put(topic, msg):
            nonlocal sent
            pubs[topic].put(msg)
            sent += 1

        g = 0
        for ep in range(2):
            put(keys.EPISODE, m.episode_start(ep, 5 + ep, (0, 0, 3), (9, 0, 3), 0.1 * g,
                                              "fake"))
            for step in range(4):
                t = 0.1 * g
                put(keys.CLOCK, m.step_clock(step, t, ep))
                put(keys.TRUTH, m.odometry((step, 0, 3), (1, 0, 0), (0, 0, 0, 1), t))
                put(keys.LIDAR_POINTS, m.pointcloud(pts, t, rings=[7, 9]))
                faces = np.zeros(35, np.float32)
                faces[3] = 0.5 if step >= 2 else 0.0  # colours change once an episode
                put(keys.OBSERVATION, m.observation(faces, t, ep, step))
                if ep == 0 and step == 1:
                    other.put(m.odometry((0, 0, 0), (0, 0, 0), (0, 0, 0, 1), t))
                    sent += 1
                g += 1
            put(keys.TRUTH, m.odometry((4, 0, 3), (1, 0, 0), (0, 0, 0, 1), 0.1 * g))
            put(keys.EPISODE, m.episode_end(ep, "success", 4, 0.1 * g))
        assert recorder.wait_written(sent, timeout=20.0)
        counters = recorder.stop()
    finally:
        recorder.stop()
        bus.close()
        session.close()
    assert counters["written"] == sent and counters["dropped"] == 0
    assert counters["other_vehicle"] == 1 and counters["view_errors"] == 0
    assert counters["scene_errors"] == 0
    files = log_files(writer.dir)
    assert len(files) == 2
    derived = 0
    for f in files:
        msgs = list(EpisodeLogReader(f).messages())
        derived += sum(x.vehicle is None for x in msgs)
        assert msgs[0].topic == "/tf_static"
        by_topic: dict[str, list] = {}
        for x in msgs:
            by_topic.setdefault(x.topic, []).append(x.decode())
        assert len(by_topic["/skyloop/uav1/viz/world"]) == 1
        assert len(by_topic["/skyloop/uav1/viz/goal"]) >= 1
        assert len(by_topic["/tf"]) == 5  # 4 steps and the terminal pose; uav2's: none
        assert [m.seconds(c.clock) for c in by_topic["/clock"]] == \
            [m.seconds(c.sim_time) for c in by_topic["/skyloop/uav1/clock"]]
        paths = by_topic["/skyloop/uav1/path"]
        assert [len(p.poses) for p in paths] == [1, 4, 5]  # poses 1 and 4, then END
        np.testing.assert_allclose([p.pose.position.x for p in paths[-1].poses],
                                   [0, 1, 2, 3, 4])
        air = by_topic["/skyloop/uav1/viz/aircraft"]
        starts = [m.seconds(x.header.stamp) for x in by_topic["/skyloop/uav1/episode"]]
        assert [a.markers[0].pose.position.x for a in air] == pytest.approx(
            [m.seconds(a.markers[0].header.stamp) - starts[0] for a in air])
        ico = by_topic["/skyloop/uav1/viz/icosahedron"]
        assert len(ico) == 2  # all free (a DELETE, with the edges), then face 3 occupied
        assert ico[0].markers[0].action == 2 and ico[0].markers[1].ns == "icosahedron_edges"
        assert len(ico[1].markers) == 1 and len(ico[1].markers[0].points) == 3 * 3  # a pentagon
        frames = set().union(*(frame_ids(x) for v in by_topic.values() for x in v))
        tree = tf_tree(by_topic["/tf"] + by_topic["/tf_static"])
        assert frames - {""} <= reachable(tree) == {"world", "base_link", "lidar"}
    assert derived == counters["derived"]


def test_world_worker_builds_worlds_in_a_process_of_its_own():
    """The recorder's world builder: a child process answering scenario names with the
    world's markers (decimated terrain coloured by height, the city's buildings), and an
    unknown scenario with an error; in a session of its own (the launcher's stop
    signals go to the recorder's process group), ended by closing its pipe."""
    import os

    from bus.ros.scene import WorldWorker
    from bus.ros.view import MARKER_ARRAY

    worker = WorldWorker()
    try:
        city, bad = worker.request("city"), worker.request("no-such-scenario")
        assert worker.request("city") is city  # one build per scenario in flight
        assert os.getpgid(worker.proc.pid) != os.getpgid(0)
        assert city.done.wait(120.0) and bad.done.wait(120.0)
        assert city.error is None and "no-such-scenario" in str(bad.error)
        world = m.decode(MARKER_ARRAY, city.result)
        by_ns = {mk.ns: mk for mk in world.markers}
        assert set(by_ns) == {"terrain", "buildings", "body"}
        assert len(by_ns["buildings"].points) % 3 == 0 and len(by_ns["buildings"].points) > 0
        assert len(by_ns["terrain"].points) <= 3 * 4000
        assert worker.proc.poll() is None
    finally:
        worker.close()
    assert worker.proc.poll() is not None


def test_world_worker_builds_the_run_scenario_first_and_once():
    """``skyloop record --scenario`` (which ``skyloop up`` passes): the worker builds
    that world before any request, not the default valley (a short run on a loaded
    machine ended before both were built: its log had no world); the request is then
    answered from what was built. A family is not built (its worlds are drawn): its
    template is, to warm the kernels. A scenario that fails is answered with its error."""
    import io

    from bus.ros.scene import PREBUILT, SitlScene, serve

    class Counting(SitlScene):
        def __init__(self) -> None:
            super().__init__()
            self.built: list[str] = []

        def world(self, scenario: str):  # noqa: ANN201 - the real world, counted
            self.built.append(scenario)
            return super().world(scenario)

    scene, out = Counting(), io.BytesIO()
    serve(io.BytesIO(b"dynamic\n"), out, scene, prebuilt=("dynamic",))
    assert scene.built == ["dynamic"] and PREBUILT == ("valley",)
    assert out.getvalue()[0] == 0 and b"dynamic" in out.getvalue()[:20]
    scene, out = Counting(), io.BytesIO()
    serve(io.BytesIO(b"nope\n"), out, scene, prebuilt=("family:city", "nope"))
    assert scene.built[0] == "city"  # the template, not "family:city"
    assert out.getvalue()[0] == 1 and b"nope" in out.getvalue()


# ------------------------------------------------------------------ a real run
@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """``skyloop up`` on the dynamic scenario (aircraft crossing), scripted policy,
    3 short episodes (long enough for the recorder's worker to build the world on a
    loaded machine), recorded with lz4 chunks (not the default zstd: the flag reaches the
    recorder); returns the run directory and the wall-clock window."""
    import socket
    import subprocess
    import sys
    import time
    from pathlib import Path

    from loopback import free_port

    out = tmp_path_factory.mktemp("ros_log")
    udp = [free_port(socket.SOCK_DGRAM) for _ in range(4)]
    cmd = [sys.executable, "-m", "skyloop", "up", "--hub", f"tcp/127.0.0.1:{free_port()}",
           "--api-port", str(udp[0]), "--api-local-port", str(udp[1]),
           "--gcs-port", str(udp[2]), "--gcs-local-port", str(udp[3]),
           "--scenario", "dynamic", "--episodes", "3", "--max-steps", "60",
           "--policy", "scripted", "--log-dir", str(out), "--log-compression", "lz4"]
    t0 = time.time_ns()
    proc = subprocess.run(cmd, cwd=Path(__file__).resolve().parents[2],
                          capture_output=True, text=True, timeout=300)
    t1 = time.time_ns()
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (run,) = out.glob("run-*")
    return run, (t0, t1)


@pytest.fixture(scope="module")
def flight_messages(flight):
    """Every message of the run read back with rosbags (types from the log itself):
    (topic, type, log time, message) in log-time order."""
    from rosbags.highlevel import AnyReader

    with AnyReader([flight[0]]) as reader:
        return [(c.topic, c.msgtype, t, reader.deserialize(raw, c.msgtype))
                for c, t, raw in reader.messages()]


def test_up_log_compression_reaches_the_recorder(flight):
    """`skyloop up --log-compression lz4`: every chunk of the run is lz4; without the
    flag the recorder is asked for zstd."""
    from mcap.reader import make_reader

    from skyloop.cli.stack import parse_node

    (path,) = flight[0].glob("*.mcap")
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert chunks and {c.compression for c in chunks} == {"lz4"}
    assert parse_node(["up"]).log_compression == "zstd"


def test_flight_log_topics_are_there_and_decode(flight_messages):
    from bus.ros.view import CLOCK_MESSAGE, MARKER_ARRAY, PATH, TF_MESSAGE

    types = {topic: kind for topic, kind, _, _ in flight_messages}
    v = "/skyloop/uav1"
    expected = {"/tf": TF_MESSAGE, "/tf_static": TF_MESSAGE, "/clock": CLOCK_MESSAGE,
                f"{v}/viz/world": MARKER_ARRAY, f"{v}/viz/goal": MARKER_ARRAY,
                f"{v}/viz/aircraft": MARKER_ARRAY, f"{v}/viz/icosahedron": MARKER_ARRAY,
                f"{v}/path": PATH, f"{v}/lidar/points": m.POINTCLOUD2}
    assert {t: types.get(t) for t in expected} == expected
    count = {t: sum(x[0] == t for x in flight_messages) for t in types}
    assert count["/tf_static"] == 1 and count[f"{v}/viz/world"] == 1
    assert count[f"{v}/viz/goal"] == 3 and count["/clock"] == count[f"{v}/clock"]
    assert count["/tf"] == count[f"{v}/truth"] == count[f"{v}/viz/aircraft"]
    world = next(x[3] for x in flight_messages if x[0] == f"{v}/viz/world")
    kinds = {mk.ns: mk for mk in world.markers}
    assert set(kinds) == {"terrain", "body"}  # the dynamic world: terrain, no obstacles
    terrain = kinds["terrain"]
    assert terrain.type == 11 and len(terrain.points) % 3 == 0
    assert 1000 <= len(terrain.points) // 3 <= 4000 and len(terrain.colors) == len(terrain.points)
    assert kinds["body"].header.frame_id == "base_link" and kinds["body"].frame_locked


def test_flight_log_every_frame_is_in_the_tf_tree(flight_messages):
    """Every frame id a message of the log names is reachable from ``world`` through
    /tf and /tf_static, and each scan has its vehicle pose at its own stamp (an exact
    TF lookup, no extrapolation)."""
    tree = tf_tree(x[3] for x in flight_messages if x[0] in ("/tf", "/tf_static"))
    assert reachable(tree) == {"world", "base_link", "lidar"}
    used: dict[str, set[str]] = {}
    for topic, _, _, msg in flight_messages:
        for frame in frame_ids(msg):
            used.setdefault(frame, set()).add(topic)
    assert "" not in used, used.get("")  # nothing in this log is without a frame
    assert set(used) <= reachable(tree), {f: used[f] for f in set(used) - reachable(tree)}
    tf_stamps = {m.nanoseconds(t.header.stamp) for topic, _, _, msg in flight_messages
                 if topic == "/tf" for t in msg.transforms}
    clouds = [msg for topic, _, _, msg in flight_messages if topic.endswith("lidar/points")]
    assert clouds and all(m.nanoseconds(c.header.stamp) in tf_stamps for c in clouds)


def test_flight_log_stamps_are_sim_time_and_log_times_wall_clock(flight, flight_messages):
    """The convention (docs/interfaces.md, "Logs in 3D"): log time = when the recorder
    received the message (wall clock, inside the run's window); header stamps = stack
    time from 0; /clock carries the step clock's stack time, in order; a derived
    message has the log time of the message it was derived from."""
    t0, t1 = flight[1]
    assert all(t0 <= t <= t1 for _, _, t, _ in flight_messages)
    stamps = [m.seconds(msg.header.stamp) for _, _, _, msg in flight_messages
              if hasattr(msg, "header")]
    assert max(stamps) < 3 * 60 * 0.1 + 1  # 3 episodes of at most 60 steps of 0.1 s
    clock = [(t, m.nanoseconds(msg.clock)) for topic, _, t, msg in flight_messages
             if topic == "/clock"]
    steps = [(t, m.nanoseconds(msg.sim_time)) for topic, _, t, msg in flight_messages
             if topic == "/skyloop/uav1/clock"]
    assert clock == steps and [c for _, c in clock] == sorted(c for _, c in clock)
    truth = {(t, m.nanoseconds(msg.header.stamp)) for topic, _, t, msg in flight_messages
             if topic.endswith("/truth")}
    tf = {(t, m.nanoseconds(msg.transforms[0].header.stamp))
          for topic, _, t, msg in flight_messages if topic == "/tf"}
    assert tf == truth


def test_flight_log_cloud_path_aircraft_and_faces(flight, flight_messages):
    from bus.log.reader import read_episodes

    episodes, report = read_episodes(flight[0])
    assert len(episodes) == 3 and report.clean, report.summary()
    clouds = [msg for topic, _, _, msg in flight_messages if topic.endswith("lidar/points")]
    assert [f.name for f in clouds[0].fields] == ["x", "y", "z", "intensity", "ring"]
    rings = np.concatenate([m.pointcloud_field(c, "ring") for c in clouds])
    assert len(rings) > 0 and rings.max() <= 15
    assert all((m.pointcloud_field(c, "intensity") == m.LIDAR_INTENSITY).all() for c in clouds)
    # the path at each END is the episode's true positions, terminal pose included
    finals, last = [], None
    for topic, _, _, msg in flight_messages:
        if topic.endswith("/path"):
            last = msg
        elif topic.endswith("/episode") and msg.event == m.END:
            finals.append(last)
    for ep, path in zip(episodes, finals, strict=True):
        truth = np.array([m.odometry_values(x.decode())[0] for x in ep.topic("truth")])
        assert len(path.poses) == ep.steps + 1
        np.testing.assert_allclose([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                                    for p in path.poses], truth)
    # aircraft at the episode's time (stamp - START stamp), as the simulator's world has them
    from sitl.world.world import World, load_scenario

    world = World(load_scenario("dynamic"))
    start_ns = None
    for topic, _, _, msg in flight_messages:
        if topic.endswith("/episode") and msg.event == m.START:
            start_ns = m.nanoseconds(msg.header.stamp)
        elif topic.endswith("/viz/aircraft"):
            t = (m.nanoseconds(msg.markers[0].header.stamp) - start_ns) / 1e9
            got = [[k.pose.position.x, k.pose.position.y, k.pose.position.z]
                   for k in msg.markers]
            np.testing.assert_allclose(got, world.aircraft_positions(t), atol=1e-9)
    faces = [msg for topic, _, _, msg in flight_messages if topic.endswith("/icosahedron")]
    assert faces and faces[0].markers[-1].ns == "icosahedron_edges"
    assert all(mk.header.frame_id == "lidar" and mk.frame_locked
               for msg in faces for mk in msg.markers)


def test_flight_log_metadata_latches_static_topics(flight):
    import yaml

    meta = yaml.safe_load((flight[0] / "metadata.yaml").read_text())
    qos = {t["topic_metadata"]["name"]: yaml.safe_load(t["topic_metadata"]["offered_qos_profiles"])
           for t in meta["rosbag2_bagfile_information"]["topics_with_message_count"]}
    for topic in ("/tf_static", "/skyloop/uav1/viz/world", "/skyloop/uav1/viz/goal"):
        assert qos[topic][0]["durability"] == 1 and qos[topic][0]["depth"] == 1  # latched
    for topic in ("/tf", "/clock", "/skyloop/uav1/odom"):
        assert qos[topic][0]["durability"] == 2  # volatile
