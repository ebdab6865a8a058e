"""bus.keys and bus.messages: the topic table, every message type's CDR round trip,
point clouds (exact, zero copy, other layouts) and the codec's speed."""

from __future__ import annotations

import time

import numpy as np
import pytest

from bus import keys
from bus import messages as m


# ------------------------------------------------------------------ keys
def test_keys_build_and_parse():
    assert keys.key("uav1", keys.LIDAR_POINTS) == "skyloop/uav1/lidar/points"
    assert keys.parse_key("skyloop/uav1/lidar/points") == ("uav1", "lidar/points")
    assert keys.ros_topic("uav1", keys.ODOM) == "/skyloop/uav1/odom"
    assert keys.parse_ros_topic("/skyloop/uav-2/cmd_vel") == ("uav-2", "cmd_vel")
    assert keys.key_all() == "skyloop/**"
    assert keys.key_all("uav1") == "skyloop/uav1/**"
    assert keys.key("*", keys.EPISODE, wildcard=True) == "skyloop/*/episode"


@pytest.mark.parametrize("bad", ["", "a/b", "*", "uav 1", "uav$", "**"])
def test_keys_reject_bad_vehicle(bad):
    with pytest.raises(ValueError):
        keys.key(bad, keys.ODOM)


def test_keys_reject_unknown():
    with pytest.raises(KeyError):
        keys.key("uav1", "nope")
    for bad in ("skyloop/uav1/nope", "other/uav1/odom", "skyloop/uav1", "/skyloop/uav1/odom"):
        with pytest.raises(ValueError):
            keys.parse_key(bad)


def test_topic_table_types_are_registered():
    expected = {
        "lidar/points": "sensor_msgs/msg/PointCloud2", "odom": "nav_msgs/msg/Odometry",
        "truth": "nav_msgs/msg/Odometry", "cmd_vel": "skyloop_msgs/msg/VelocitySetpoint",
        "goal": "geometry_msgs/msg/PoseStamped",
    }
    for name, kind in expected.items():
        assert keys.msgtype(name) == kind
    for topic in keys.TOPICS.values():
        assert topic.msgtype in m.TYPESTORE.types
        assert topic.congestion in ("block", "drop")
    assert keys.TOPICS[keys.LIDAR_POINTS].congestion == "block"


# ------------------------------------------------------------------ round trips
def _roundtrip(msg):
    data = m.encode(msg)
    assert isinstance(data, bytes)
    back = m.decode(msg.__msgtype__, data)
    assert m.encode(back) == data  # byte-identical re-encoding
    return back


def test_odometry_roundtrip():
    back = _roundtrip(m.odometry((1.0, 2.0, 3.0), (0.5, -0.5, 0.25), (0.0, 0.0, 0.6, 0.8),
                                 12.3, angular_velocity=(0.1, 0.2, 0.3)))
    pos, vel, quat = m.odometry_values(back)
    np.testing.assert_array_equal(pos, [1, 2, 3])
    np.testing.assert_array_equal(vel, [0.5, -0.5, 0.25])
    np.testing.assert_array_equal(quat, [0, 0, 0.6, 0.8])
    assert back.header.frame_id == "world" and back.child_frame_id == "base_link"
    assert m.seconds(back.header.stamp) == pytest.approx(12.3, abs=1e-9)
    assert back.twist.twist.angular.z == 0.3


def test_twist_and_pose_roundtrip():
    back = _roundtrip(m.velocity_setpoint((1.5, -2.0, 0.25), 0.75, 4.0, body=False))
    assert m.setpoint_values(back) == (1.5, -2.0, 0.25, 0.75)
    pos, quat = m.pose_values(_roundtrip(m.pose_stamped((10.0, -5.0, 2.0), 1.0)))
    np.testing.assert_array_equal(pos, [10, -5, 2])
    np.testing.assert_array_equal(quat, [0, 0, 0, 1])


def test_observation_roundtrip():
    stacked = np.arange(105, dtype=np.float32).reshape(3, 35) / 7
    back = _roundtrip(m.observation(stacked, 2.5, episode=4, step=17))
    np.testing.assert_array_equal(m.observation_values(back), stacked)
    assert (back.episode, back.step, back.frames, back.attributes) == (4, 17, 3, 35)
    single = m.observation_values(_roundtrip(m.observation(stacked[0], 0.0)))
    assert single.shape == (1, 35)


def test_episode_events_roundtrip():
    start = _roundtrip(m.episode_start(3, 2**40 + 5, (1, 2, 3), (4, 5, 6), 0.0, "valley"))
    assert (start.event, start.episode, start.seed, start.scenario) == (m.START, 3, 2**40 + 5,
                                                                         "valley")
    assert (start.goal.x, start.goal.y, start.goal.z) == (4, 5, 6)
    assert m.outcome_name(start) == "none"
    for outcome in ("success", "collision", "timeout", "aborted"):
        end = _roundtrip(m.episode_end(3, outcome, 250, 25.0))
        assert (end.event, end.steps, m.outcome_name(end)) == (m.END, 250, outcome)
    with pytest.raises(ValueError):
        m.episode_end(0, "crashed", 1, 0.0)


def test_clock_and_actor_roundtrip():
    back = _roundtrip(m.step_clock(123456, 12345.6, episode=9))
    assert (back.step, back.episode) == (123456, 9)
    assert m.seconds(back.sim_time) == pytest.approx(12345.6, abs=1e-9)
    blob = bytes(range(256)) * 40
    back = _roundtrip(m.actor_weights(blob, version=7, stamp_s=1.0, sha256="ab"))
    assert (back.version, back.format, back.sha256) == (7, "torch-state-dict", "ab")
    assert m.actor_blob(back) == blob


def test_vehicle_status_roundtrip():
    msg = m.vehicle_status(1.5, 12.3, 4, "HOLD", True, False, "setpoint_loss", False,
                           (1.0, 2.0, 0.0), [("Failsafe: setpoints lost, holding",
                                              "failsafe", "critical")], 11.7)
    back = _roundtrip(msg)
    assert (back.vehicle_time, back.last_setpoint_time, back.revision) == (12.3, 11.7, 4)
    assert (back.state, back.failsafe, back.failsafe_reason) == ("HOLD", True, "setpoint_loss")
    assert list(back.event_texts) == ["Failsafe: setpoints lost, holding"]
    assert list(back.event_severities) == [2]
    none = _roundtrip(m.vehicle_status(0.0, 0.0, 0, "DISARMED", False, True, None, False))
    assert np.isnan(none.last_setpoint_time) and not none.failsafe  # no setpoint yet


def test_time_conversion_edges():
    for t in (0.0, 1e-9, 0.999999999, 1234.5, -0.25):
        assert m.nanoseconds(m.time_msg(t)) == round(t * 1e9)
    assert m.time_msg(-0.25).nanosec < 1_000_000_000


# ------------------------------------------------------------------ point clouds
def _scan(n=28_800, seed=0):
    return np.random.default_rng(seed).normal(scale=20.0, size=(n, 3)).astype(np.float32)


def test_pointcloud_28800_exact_and_zero_copy():
    pts = _scan()
    msg = m.pointcloud(pts, 3.25, "lidar")
    assert (msg.width, msg.height, msg.point_step, msg.row_step) == (28_800, 1, 12, 345_600)
    assert [f.name for f in msg.fields] == ["x", "y", "z"] and msg.is_dense
    data = m.encode(msg)
    assert 345_600 < len(data) < 346_000
    back = m.decode(m.POINTCLOUD2, data)
    out = m.points_from_pointcloud(back)
    assert out.dtype == np.float32 and out.shape == (28_800, 3)
    np.testing.assert_array_equal(out, pts)
    assert np.shares_memory(out, back.data)  # a view, no copy
    assert not out.flags.writeable  # a view of an immutable payload


def test_pointcloud_non_finite_and_empty():
    pts = _scan(10)
    pts[3] = np.nan
    msg = m.pointcloud(pts, 0.0)
    assert not msg.is_dense
    np.testing.assert_array_equal(m.points_from_pointcloud(m.decode(m.POINTCLOUD2,
                                                                    m.encode(msg))), pts)
    empty = m.decode(m.POINTCLOUD2, m.encode(m.pointcloud(np.empty((0, 3)), 0.0)))
    assert m.points_from_pointcloud(empty).shape == (0, 3)
    with pytest.raises(ValueError):
        m.pointcloud(np.zeros((4, 2)), 0.0)


def _foreign_cloud(pts, *, big_endian=False, f64=False, row_pad=0, height=2):
    """A cloud as another driver might send it: an intensity field, padding, 2 rows."""
    fmt = (">" if big_endian else "<") + ("f8" if f64 else "f4")
    size = 8 if f64 else 4
    dt = np.dtype({"names": ["x", "y", "z", "intensity"], "formats": [fmt] * 3 + ["<f4"],
                   "offsets": [0, size, 2 * size, 3 * size + 4], "itemsize": 3 * size + 12})
    width = len(pts) // height
    rec = np.zeros(len(pts), dtype=dt)
    for i, c in enumerate("xyz"):
        rec[c] = pts[:, i]
    rows = rec.view(np.uint8).reshape(height, width * dt.itemsize)
    data = np.concatenate([rows, np.zeros((height, row_pad), np.uint8)], axis=1).reshape(-1)
    kind = 8 if f64 else 7
    fields = [m.PointField(name=c, offset=o, datatype=kind, count=1)
              for c, o in zip("xyz", (0, size, 2 * size), strict=True)]
    fields.append(m.PointField(name="intensity", offset=3 * size + 4, datatype=7, count=1))
    return m.PointCloud2(header=m.header(0.0, "velodyne"), height=height, width=width,
                         fields=fields, is_bigendian=big_endian, point_step=dt.itemsize,
                         row_step=width * dt.itemsize + row_pad, data=data, is_dense=True)


@pytest.mark.parametrize("opts", [{}, {"big_endian": True}, {"f64": True}, {"row_pad": 7}])
def test_points_from_foreign_layouts(opts):
    pts = _scan(64, seed=1)
    msg = m.decode(m.POINTCLOUD2, m.encode(_foreign_cloud(pts, **opts)))
    np.testing.assert_array_equal(m.points_from_pointcloud(msg), pts)


def test_pointcloud_codec_is_sub_millisecond():
    pts = _scan()
    msg = m.pointcloud(pts, 0.0)
    data = m.encode(msg)

    def median_ms(fn, n=40):
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return 1e3 * float(np.median(times))

    enc = median_ms(lambda: m.encode(m.pointcloud(pts, 0.0)))
    dec = median_ms(lambda: m.points_from_pointcloud(m.decode(m.POINTCLOUD2, data)))
    assert enc < 1.0 and dec < 1.0, (enc, dec)


# ------------------------------------------------------------------ errors and schemas
@pytest.mark.parametrize("payload", [b"", b"\x00", b"garbage!", b"\x00\x01\x00\x00\xff\xff"])
def test_decode_rejects_garbage(payload):
    with pytest.raises(Exception):  # noqa: B017 - any error, never a silent object
        m.decode(m.ODOMETRY, payload)


def test_decode_rejects_truncated_cloud():
    data = m.encode(m.pointcloud(_scan(100), 0.0))
    with pytest.raises(Exception):  # noqa: B017
        m.points_from_pointcloud(m.decode(m.POINTCLOUD2, data[: len(data) // 2]))


def test_msgdef_is_full_ros2_text():
    text = m.msgdef(m.EPISODE_EVENT)
    assert text.startswith("uint8 START=0")
    for dep in ("MSG: std_msgs/Header", "MSG: builtin_interfaces/Time", "MSG: geometry_msgs/Point"):
        assert dep in text
    assert "MSG: sensor_msgs/PointField" in m.msgdef(m.POINTCLOUD2)


def test_yaw_of_quaternion():
    import math

    for yaw in (-3.0, -1.2, 0.0, 0.7, 2.9):
        q = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        assert m.yaw_of(q) == pytest.approx(yaw, abs=1e-12)
