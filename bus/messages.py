"""Message types and the CDR codec: the rosbags ROS 2 Humble type store plus the project
``.msg`` types in ``bus/msg/`` (package ``skyloop_msgs``).

``encode(msg) -> bytes`` and ``decode(type_name, data)`` are the only serialisation
path of the stack. The constructors below build the messages the stack sends and the
extractors turn them back into numpy arrays, so no other package touches a message's
field layout.

Conventions: header stamps are the stack time (sim time: seconds of control steps
since the sim started, so they begin at the epoch, 1970) stored as
``builtin_interfaces/Time``; what a log does with them: docs/interfaces.md, "Logs in
3D". Frames: ``world`` (ENU), ``base_link`` (body FLU), ``lidar`` (the VLP-16, at
``base_link``); every message with a position or direction names one of them
(EpisodeEvent and VehicleStatus ``world``, Observation ``base_link``), the rest ``''``
(ActorWeights: no geometry). Odometry carries the velocity in the *world* frame
(``frame_id``), not in ``child_frame_id`` as REP 105 has it; the stack never reads it
otherwise.

Measured (this machine, other core busy): encode of a 28,800-point cloud about
0.03 ms, decode plus :func:`points_from_pointcloud` about 0.02 ms (zero copy).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from bus.task import TASK, StepRecord, TaskSpec

MSG_DIR = Path(__file__).resolve().parent / "msg"
PROJECT_PACKAGE = "skyloop_msgs"

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
OBSERVATION = f"{PROJECT_PACKAGE}/msg/Observation"
EPISODE_EVENT = f"{PROJECT_PACKAGE}/msg/EpisodeEvent"
STEP_CLOCK = f"{PROJECT_PACKAGE}/msg/StepClock"
ACTOR_WEIGHTS = f"{PROJECT_PACKAGE}/msg/ActorWeights"
VEHICLE_STATUS = f"{PROJECT_PACKAGE}/msg/VehicleStatus"
PARAMETER = f"{PROJECT_PACKAGE}/msg/Parameter"
VEHICLE_COMMAND = f"{PROJECT_PACKAGE}/msg/VehicleCommand"
COMMAND_ACK = f"{PROJECT_PACKAGE}/msg/CommandAck"
VELOCITY_SETPOINT = f"{PROJECT_PACKAGE}/msg/VelocitySetpoint"
STEP_RECORD = f"{PROJECT_PACKAGE}/msg/StepRecord"
PROJECT_TYPES = (OBSERVATION, EPISODE_EVENT, STEP_CLOCK, ACTOR_WEIGHTS, VEHICLE_STATUS,
                 PARAMETER, VEHICLE_COMMAND, COMMAND_ACK, VELOCITY_SETPOINT, STEP_RECORD)

START, END = 0, 1
OUTCOMES = {"none": 0, "success": 1, "collision": 2, "timeout": 3, "aborted": 4}
OUTCOME_NAMES = {v: k for k, v in OUTCOMES.items()}

_FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
_FLOAT64 = 8
_LITTLE = sys.byteorder == "little"


def _build_typestore() -> Any:
    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for name in PROJECT_TYPES:
        path = MSG_DIR / f"{name.rsplit('/', 1)[1]}.msg"
        types.update(get_types_from_msg(path.read_text(), name))
    store.register(types)
    return store


#: The type store (ROS 2 Humble + skyloop_msgs). Treat as read-only.
TYPESTORE = _build_typestore()
_T = TYPESTORE.types
Time = _T["builtin_interfaces/msg/Time"]
Header = _T["std_msgs/msg/Header"]
Point = _T["geometry_msgs/msg/Point"]
Vector3 = _T["geometry_msgs/msg/Vector3"]
Quaternion = _T["geometry_msgs/msg/Quaternion"]
Pose = _T["geometry_msgs/msg/Pose"]
Twist = _T["geometry_msgs/msg/Twist"]
PointField = _T["sensor_msgs/msg/PointField"]
PointCloud2 = _T[POINTCLOUD2]
Odometry = _T[ODOMETRY]
PoseStamped = _T[POSE_STAMPED]
Observation = _T[OBSERVATION]
EpisodeEvent = _T[EPISODE_EVENT]
StepClock = _T[STEP_CLOCK]
ActorWeights = _T[ACTOR_WEIGHTS]
VehicleStatus = _T[VEHICLE_STATUS]
Parameter = _T[PARAMETER]
VehicleCommand = _T[VEHICLE_COMMAND]
CommandAck = _T[COMMAND_ACK]
VelocitySetpoint = _T[VELOCITY_SETPOINT]
StepRecordMsg = _T[STEP_RECORD]
FRAME_BODY, FRAME_WORLD = VelocitySetpoint.FRAME_BODY, VelocitySetpoint.FRAME_WORLD
_ZERO_COV = np.zeros(36, dtype=np.float64)


# ----------------------------------------------------------------------------- codec
def encode(msg: Any) -> bytes:
    """Serialise a message (any type of :data:`TYPESTORE`) to CDR bytes."""
    return bytes(TYPESTORE.serialize_cdr(msg, msg.__msgtype__))


def decode(type_name: str, data: bytes | bytearray | memoryview) -> Any:
    """Deserialise CDR ``data`` as ``type_name``.

    Raises on a payload that does not decode (truncated, wrong type, unknown type);
    array fields are numpy views into ``data`` (read-only when ``data`` is ``bytes``).
    """
    if type_name not in _T:
        raise KeyError(f"unknown message type {type_name!r}")
    if len(data) < 4:
        raise ValueError(f"{type_name}: {len(data)}-byte payload is shorter than a CDR header")
    return TYPESTORE.deserialize_cdr(data, type_name)


def msgdef(type_name: str) -> str:
    """Full ROS 2 ``.msg`` definition of ``type_name`` with its dependencies appended
    (``====`` / ``MSG: pkg/Type`` blocks): the MCAP ``ros2msg`` schema text."""
    return TYPESTORE.generate_msgdef(type_name, ros_version=2)[0]


# ----------------------------------------------------------------------------- times
def time_msg(t_s: float) -> Any:
    """Float seconds -> ``builtin_interfaces/Time`` (nanosecond rounding)."""
    ns = round(float(t_s) * 1e9)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def seconds(t: Any) -> float:
    """``builtin_interfaces/Time`` -> float seconds."""
    return t.sec + t.nanosec * 1e-9


def nanoseconds(t: Any) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds."""
    return t.sec * 1_000_000_000 + t.nanosec


def header(stamp_s: float, frame_id: str = "") -> Any:
    """``std_msgs/Header`` with the stamp in float seconds."""
    return Header(stamp=time_msg(stamp_s), frame_id=frame_id)


def _vec3(v: Sequence[float], kind: Any) -> Any:
    x, y, z = (float(c) for c in v)
    return kind(x=x, y=y, z=z)


def _quat(q: Sequence[float]) -> Any:
    x, y, z, w = (float(c) for c in q)
    return Quaternion(x=x, y=y, z=z, w=w)


# ----------------------------------------------------------------------------- clouds
#: PointField datatypes by numpy kind (sensor_msgs/PointField constants).
_FIELD_KINDS = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_UINT16 = 4
#: The intensity of every simulated return (see :func:`pointcloud`).
LIDAR_INTENSITY = 100.0
#: The VLP-16 layout of ``velodyne_pointcloud``'s ROS 2 PointcloudXYZIR: x, y, z,
#: intensity float32 at 0, 4, 8, 12, ring uint16 at 16, ``point_step`` 18 (no padding,
#: as ``PointCloud2Modifier.setPointCloud2Fields`` lays fields out).
_XYZIR = np.dtype({"names": ["x", "y", "z", "intensity", "ring"],
                   "formats": ["<f4", "<f4", "<f4", "<f4", "<u2"],
                   "offsets": [0, 4, 8, 12, 16], "itemsize": 18})
_XYZIR_FIELDS = tuple(PointField(name=name, offset=_XYZIR.fields[name][1],
                                  datatype=_UINT16 if name == "ring" else _FLOAT32, count=1)
                      for name in _XYZIR.names)


def pointcloud(points: np.ndarray, stamp_s: float, frame_id: str = "lidar", *,
               rings: np.ndarray | None = None,
               intensity: float | np.ndarray = LIDAR_INTENSITY) -> Any:
    """(N, 3) points -> ``PointCloud2``, one row, dense if every point is finite.

    Without ``rings``: x, y, z float32 (``point_step`` 12; the float32 buffer is used as
    it is, no per-point work). With ``rings`` ((N,) laser index, 0 = lowest beam): the
    layout a VLP-16 driver publishes (``velodyne_pointcloud`` XYZIR: x, y, z,
    ``intensity`` float32, ``ring`` uint16, ``point_step`` 18). ``intensity``: the
    simulator has no reflectivity model (one diffuse material everywhere), so every
    return carries the same calibrated reflectivity, :data:`LIDAR_INTENSITY` (100 on the
    VLP-16's scale: 0-100 diffuse, 101-255 retro-reflective); a scalar or (N,) array.
    """
    pts = np.ascontiguousarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    n = pts.shape[0]
    dense = bool(np.isfinite(pts).all())
    if rings is not None:
        ring = np.asarray(rings).reshape(-1)
        if ring.shape[0] != n:
            raise ValueError(f"{ring.shape[0]} rings for {n} points")
        step = _XYZIR.itemsize
        data = np.empty(n * step, dtype=np.uint8)
        # x, y, z, intensity as one strided float32 block, the ring behind it: two
        # copies instead of five field by field
        if n:
            xyzi = np.ndarray((n, 4), dtype="<f4", buffer=data, strides=(step, 4))
            xyzi[:, :3] = pts
            xyzi[:, 3] = intensity
            np.ndarray((n,), dtype="<u2", buffer=data, offset=16, strides=(step,))[:] = ring
        return PointCloud2(
            header=header(stamp_s, frame_id), height=1, width=n, fields=[*_XYZIR_FIELDS],
            is_bigendian=False, point_step=step, row_step=step * n, data=data,
            is_dense=dense)
    if not _LITTLE:  # the cloud says is_bigendian=False; keep the bytes little-endian
        pts = pts.astype("<f4")
    fields = [PointField(name=c, offset=4 * i, datatype=_FLOAT32, count=1)
              for i, c in enumerate("xyz")]
    return PointCloud2(
        header=header(stamp_s, frame_id), height=1, width=n, fields=fields,
        is_bigendian=False, point_step=12, row_step=12 * n,
        data=pts.reshape(-1).view(np.uint8), is_dense=dense,
    )


def elevation_rings(points: np.ndarray, min_elevation_deg: float, max_elevation_deg: float,
                    channels: int) -> np.ndarray:
    """The laser ring (0 = lowest beam) of each sensor-frame return of a spinning LiDAR
    whose ``channels`` beams are evenly spaced from ``min_elevation_deg`` to
    ``max_elevation_deg`` (the VLP-16: 16 beams, -15 to +15 degrees, 2 apart).

    A return lies on its beam (range noise moves it along the ray), so its elevation
    is the beam's up to float32 rounding (~1e-7 rad against 2-degree spacing): the ring
    is exact. (N,) uint16."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if channels <= 1 or len(p) == 0:
        return np.zeros(len(p), dtype=np.uint16)
    el = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    lo = math.radians(min_elevation_deg)
    step = (math.radians(max_elevation_deg) - lo) / (channels - 1)
    ring = np.rint((el - lo) / step)
    return np.clip(np.nan_to_num(ring), 0, channels - 1).astype(np.uint16)


def pointcloud_field(msg: Any, name: str) -> np.ndarray:
    """One scalar field of every point of a ``PointCloud2`` (e.g. ``'ring'``,
    ``'intensity'``) as a 1-D array of the field's type; ``ValueError`` if absent."""
    by_name = {f.name: f for f in msg.fields}
    f = by_name.get(name)
    if f is None:
        raise ValueError(f"PointCloud2 has no field {name!r} (has {sorted(by_name)})")
    if f.datatype not in _FIELD_KINDS:
        raise ValueError(f"field {name!r} has unknown datatype {f.datatype}")
    rows = _cloud_rows(msg)
    kind = np.dtype(_FIELD_KINDS[f.datatype]).newbyteorder(">" if msg.is_bigendian else "<")
    dt = np.dtype({"names": [name], "formats": [kind], "offsets": [f.offset],
                   "itemsize": msg.point_step})
    return rows.view(dt).reshape(-1)[name].astype(kind.newbyteorder("="))


def _cloud_rows(msg: Any) -> np.ndarray:
    """The cloud's point bytes, row padding removed: (height * width * point_step,) uint8."""
    data = np.asarray(msg.data, dtype=np.uint8)
    if msg.height * msg.width == 0:
        return np.empty(0, dtype=np.uint8)
    if msg.point_step < 1 or data.size < msg.height * msg.row_step \
            or msg.row_step < msg.width * msg.point_step:
        raise ValueError("PointCloud2 data shorter than height * row_step")
    rows = data[: msg.height * msg.row_step].reshape(msg.height, msg.row_step)
    return np.ascontiguousarray(rows[:, : msg.width * msg.point_step]).reshape(-1)


def points_from_pointcloud(msg: Any) -> np.ndarray:
    """``PointCloud2`` -> (N, 3) float32 x, y, z.

    Zero copy for the layout :func:`pointcloud` writes without rings (x, y, z float32 at
    offsets 0, 4, 8, point_step 12, no row padding, host byte order): the result is then
    a view of the message buffer, read-only if the payload was ``bytes``. x, y, z
    float32 at 0, 4, 8 with a longer point (the VLP-16 layout with intensity and ring):
    one strided copy. Other layouts (padding, float64, big-endian) are converted with
    one vectorised copy.
    """
    by_name = {f.name: f for f in msg.fields}
    missing = [c for c in "xyz" if c not in by_name]
    if missing:
        raise ValueError(f"PointCloud2 has no field(s) {missing}")
    n = msg.height * msg.width
    data = np.asarray(msg.data, dtype=np.uint8)
    if n == 0:
        return np.empty((0, 3), dtype=np.float32)
    xyz = [by_name[c] for c in "xyz"]
    if msg.point_step < 1 or data.size < msg.height * msg.row_step \
            or msg.row_step < msg.width * msg.point_step:
        raise ValueError("PointCloud2 data shorter than height * row_step")
    same_order = bool(msg.is_bigendian) != _LITTLE
    packed_xyz = all(f.datatype == _FLOAT32 and f.offset == 4 * i for i, f in enumerate(xyz))
    if same_order and packed_xyz and msg.row_step == msg.point_step * msg.width:
        if msg.point_step == 12:
            return data[: 12 * n].view(np.float32).reshape(n, 3)
        if msg.point_step >= 12:
            view = np.ndarray((n, 3), dtype=np.float32, buffer=data[: msg.point_step * n],
                              strides=(msg.point_step, 4))
            return np.array(view, dtype=np.float32, order="C")
    kinds = {_FLOAT32: "f4", _FLOAT64: "f8"}
    if any(f.datatype not in kinds for f in xyz):
        raise ValueError("x, y, z must be FLOAT32 or FLOAT64")
    endian = ">" if msg.is_bigendian else "<"
    dt = np.dtype({"names": list("xyz"), "formats": [endian + kinds[f.datatype] for f in xyz],
                   "offsets": [f.offset for f in xyz], "itemsize": msg.point_step})
    rec = _cloud_rows(msg).view(dt).reshape(-1)
    out = np.empty((n, 3), dtype=np.float32)
    for i, c in enumerate("xyz"):
        out[:, i] = rec[c]
    return out


# ----------------------------------------------------------------------------- state
def odometry(position: Sequence[float], velocity: Sequence[float],
             quaternion_xyzw: Sequence[float], stamp_s: float, frame_id: str = "world",
             child_frame_id: str = "base_link",
             angular_velocity: Sequence[float] = (0.0, 0.0, 0.0)) -> Any:
    """``nav_msgs/Odometry``: position and linear velocity in world ENU (``frame_id``),
    orientation as (x, y, z, w), body angular rates; covariances zero (unknown)."""
    pose = _T["geometry_msgs/msg/PoseWithCovariance"](
        pose=Pose(position=_vec3(position, Point), orientation=_quat(quaternion_xyzw)),
        covariance=_ZERO_COV.copy())
    twist = _T["geometry_msgs/msg/TwistWithCovariance"](
        twist=Twist(linear=_vec3(velocity, Vector3), angular=_vec3(angular_velocity, Vector3)),
        covariance=_ZERO_COV.copy())
    return Odometry(header=header(stamp_s, frame_id), child_frame_id=child_frame_id,
                    pose=pose, twist=twist)


def odometry_values(msg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``Odometry`` -> (position (3,), velocity (3,), quaternion_xyzw (4,)) float64."""
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    v = msg.twist.twist.linear
    return (np.array([p.x, p.y, p.z]), np.array([v.x, v.y, v.z]),
            np.array([q.x, q.y, q.z, q.w]))


def yaw_of(quaternion_xyzw) -> float:
    """Yaw (rotation about z, rad, CCW from x) of a ROS ``(x, y, z, w)`` quaternion."""
    x, y, z, w = (float(c) for c in quaternion_xyzw)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def velocity_setpoint(velocity: Sequence[float], yaw: float, stamp_s: float, body: bool,
                      heading: bool = False) -> Any:
    """``VelocitySetpoint``: ``velocity`` (3,) m/s in the body-horizontal FLU frame
    (``body``) or world ENU; ``yaw`` a CCW yaw rate (rad/s), or with ``heading`` a
    heading target (rad); ``stamp_s`` the stack time of the step it answers."""
    return VelocitySetpoint(header=header(stamp_s, "base_link" if body else "world"),
                            frame=FRAME_BODY if body else FRAME_WORLD,
                            velocity=_vec3(velocity, Vector3), heading=bool(heading),
                            yaw=float(yaw))


def setpoint_values(msg: Any) -> tuple[float, float, float, float]:
    """``VelocitySetpoint`` -> (vx, vy, vz, yaw) in its frame (yaw: rate or heading)."""
    v = msg.velocity
    return (v.x, v.y, v.z, msg.yaw)


def is_action(msg: Any) -> bool:
    """A ``VelocitySetpoint`` of the policy's kind: body frame, yaw rate (the env's and
    the stack's action; what training from logs learns from)."""
    return msg.frame == FRAME_BODY and not msg.heading


def pose_stamped(position: Sequence[float], stamp_s: float,
                 quaternion_xyzw: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
                 frame_id: str = "world") -> Any:
    """``geometry_msgs/PoseStamped`` (goals): position in world ENU."""
    return PoseStamped(header=header(stamp_s, frame_id), pose=Pose(
        position=_vec3(position, Point), orientation=_quat(quaternion_xyzw)))


def pose_values(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """``PoseStamped`` -> (position (3,), quaternion_xyzw (4,)) float64."""
    p, q = msg.pose.position, msg.pose.orientation
    return np.array([p.x, p.y, p.z]), np.array([q.x, q.y, q.z, q.w])


# ----------------------------------------------------------------------------- project
#: The Observation fields that say how its values were scaled (see Observation.msg).
SCALING_FIELDS = ("radius", "altitude_scale", "angle_scale", "centre_angles", "encoding")


def observation(values: np.ndarray, stamp_s: float, episode: int = 0, step: int = 0,
                frame_id: str = "base_link", scaling: Mapping[str, Any] | None = None) -> Any:
    """``skyloop_msgs/Observation`` from a (attributes,) or (frames, attributes) array;
    ``scaling`` (the :data:`SCALING_FIELDS` of the ``ObservationConfig`` that made the
    values) is recorded with them; without it the message says "not recorded"."""
    arr = np.asarray(values, dtype=np.float32)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2:
        raise ValueError(f"observation must be 1-D or 2-D, got {arr.shape}")
    s = dict(scaling) if scaling is not None else {}
    return Observation(header=header(stamp_s, frame_id), episode=int(episode), step=int(step),
                       frames=arr.shape[0], attributes=arr.shape[1],
                       values=np.ascontiguousarray(arr).reshape(-1),
                       radius=float(s.get("radius", 0.0)),
                       altitude_scale=float(s.get("altitude_scale", 0.0)),
                       angle_scale=float(s.get("angle_scale", 0.0)),
                       centre_angles=bool(s.get("centre_angles", False)),
                       encoding=str(s.get("encoding", "")))


def observation_scaling(msg: Any) -> dict[str, Any] | None:
    """The scaling an ``Observation`` records (:data:`SCALING_FIELDS`), None when it was
    not recorded."""
    if not msg.radius > 0.0:
        return None
    return {name: getattr(msg, name) for name in SCALING_FIELDS}


def observation_values(msg: Any) -> np.ndarray:
    """``Observation`` -> (frames, attributes) float32 (a view of the message buffer)."""
    values = np.asarray(msg.values, dtype=np.float32)
    if values.size != msg.frames * msg.attributes:
        raise ValueError(f"{values.size} values for {msg.frames} x {msg.attributes}")
    return values.reshape(msg.frames, msg.attributes)


def episode_start(episode: int, seed: int, start: Sequence[float], goal: Sequence[float],
                  stamp_s: float, scenario: str = "", task: TaskSpec = TASK) -> Any:
    """``EpisodeEvent`` START with the seed, start and goal positions (world ENU) and the
    episode limits of ``task`` it runs under (``max_steps`` inf: no limit, recorded 0)."""
    steps = 0 if math.isinf(task.max_steps) else int(task.max_steps)
    return EpisodeEvent(header=header(stamp_s, "world"), event=START, episode=int(episode),
                        seed=int(seed), scenario=scenario, start=_vec3(start, Point),
                        goal=_vec3(goal, Point), outcome=OUTCOMES["none"], steps=0,
                        max_steps=steps, goal_radius=float(task.goal_radius),
                        goal_max_altitude=float(task.goal_max_altitude))


def episode_limits(msg: Any) -> dict[str, float] | None:
    """The episode limits an ``EpisodeEvent`` START records (``max_steps`` inf when
    unlimited), None when it records none (goal_radius 0)."""
    if not msg.goal_radius > 0.0:
        return None
    return {"max_steps": float(msg.max_steps) if msg.max_steps else math.inf,
            "goal_radius": float(msg.goal_radius),
            "goal_max_altitude": float(msg.goal_max_altitude)}


def episode_end(episode: int, outcome: str, steps: int, stamp_s: float,
                seed: int = 0, scenario: str = "") -> Any:
    """``EpisodeEvent`` END; ``outcome`` in success, collision, timeout, aborted."""
    if outcome not in OUTCOMES or outcome == "none":
        raise ValueError(f"outcome must be one of {sorted(set(OUTCOMES) - {'none'})}")
    zero = Point(x=0.0, y=0.0, z=0.0)
    return EpisodeEvent(header=header(stamp_s, "world"), event=END, episode=int(episode),
                        seed=int(seed), scenario=scenario, start=zero, goal=zero,
                        outcome=OUTCOMES[outcome], steps=int(steps), max_steps=0,
                        goal_radius=0.0, goal_max_altitude=0.0)


def outcome_name(msg: Any) -> str:
    """Outcome of an ``EpisodeEvent`` as a string (``'none'`` for START)."""
    return OUTCOME_NAMES.get(int(msg.outcome), f"unknown({msg.outcome})")


def step_clock(step: int, sim_time_s: float, episode: int = 0) -> Any:
    """``skyloop_msgs/StepClock``: lockstep step index and sim time."""
    if not math.isfinite(sim_time_s):
        raise ValueError("sim_time_s must be finite")
    return StepClock(sim_time=time_msg(sim_time_s), episode=int(episode), step=int(step))


def step_record(record: StepRecord, stamp_s: float) -> Any:
    """``skyloop_msgs/StepRecord`` of a :class:`bus.task.StepRecord`, stamped ``stamp_s``
    (the stack time after the step)."""
    return StepRecordMsg(header=header(stamp_s, "world"), episode=int(record.episode),
                         step=int(record.step), distance_before=record.distance_before,
                         distance=record.distance, altitude=record.altitude, h=record.h,
                         g=record.g, collided=record.collided,
                         outcome=OUTCOMES[record.outcome or "none"])


def step_record_values(msg: Any) -> StepRecord:
    """``StepRecord`` message -> :class:`bus.task.StepRecord`; ``ValueError`` on an
    outcome it cannot carry (aborted, unknown) or a non-finite value."""
    outcome = OUTCOME_NAMES.get(int(msg.outcome))
    if outcome is None or outcome == "aborted":
        raise ValueError(f"step record outcome {msg.outcome}")
    values = (msg.distance_before, msg.distance, msg.altitude, msg.h, msg.g)
    if not all(math.isfinite(v) for v in values):
        raise ValueError("non-finite step record")
    return StepRecord(int(msg.episode), int(msg.step), *(float(v) for v in values),
                      bool(msg.collided), None if outcome == "none" else outcome)


def actor_weights(blob: bytes | bytearray | memoryview | np.ndarray, version: int,
                  stamp_s: float = 0.0, fmt: str = "torch-state-dict",
                  sha256: str = "") -> Any:
    """``skyloop_msgs/ActorWeights``: an opaque weights blob with its version."""
    data = np.frombuffer(blob, dtype=np.uint8) if not isinstance(blob, np.ndarray) \
        else np.ascontiguousarray(blob).reshape(-1).view(np.uint8)
    return ActorWeights(header=header(stamp_s), version=int(version), format=fmt,
                        sha256=sha256, blob=data)


def actor_blob(msg: Any) -> bytes:
    """``ActorWeights`` -> the blob as ``bytes``."""
    return np.asarray(msg.blob, dtype=np.uint8).tobytes()


# ----------------------------------------------------------------------------- vehicle
#: STATUSTEXT severities (MAV_SEVERITY) by name.
SEVERITIES = {"emergency": 0, "alert": 1, "critical": 2, "error": 3, "warning": 4,
              "notice": 5, "info": 6, "debug": 7}


def vehicle_status(stamp_s: float, vehicle_time: float, revision: int, state: str,
                   armed: bool, landed: bool, failsafe_reason: str | None, crashed: bool,
                   home: Sequence[float] = (0.0, 0.0, 0.0),
                   events: Sequence[tuple[str, str, str]] = (),
                   last_setpoint_time: float = math.nan) -> Any:
    """``skyloop_msgs/VehicleStatus``; ``events``: (text, kind, severity name) each;
    ``last_setpoint_time``: the newest accepted setpoint's vehicle time (NaN: none)."""
    return VehicleStatus(
        header=header(stamp_s, "world"), vehicle_time=float(vehicle_time),
        last_setpoint_time=float(last_setpoint_time), revision=int(revision),
        state=str(state), armed=bool(armed), landed=bool(landed),
        failsafe=failsafe_reason is not None, failsafe_reason=failsafe_reason or "",
        crashed=bool(crashed), home=np.array(home, dtype=np.float64).reshape(3),
        event_texts=[t for t, _, _ in events], event_kinds=[k for _, k, _ in events],
        event_severities=np.array([SEVERITIES.get(s, 6) for _, _, s in events], np.uint8))


def vehicle_command(command: str, mode: str = "", param1: float = math.nan) -> Any:
    """``skyloop_msgs/VehicleCommand`` (see the .msg for the commands)."""
    return VehicleCommand(command=str(command), mode=str(mode), param1=float(param1))


def command_ack(accepted: bool, reason: str, state: str, armed: bool, landed: bool,
                failsafe: bool, revision: int) -> Any:
    """``skyloop_msgs/CommandAck``: a verdict and the commander's state after it."""
    return CommandAck(accepted=bool(accepted), reason=str(reason), state=str(state),
                      armed=bool(armed), landed=bool(landed), failsafe=bool(failsafe),
                      revision=int(revision))


def parameter(name: str, value: float) -> Any:
    """``skyloop_msgs/Parameter``: one parameter set (``bus.params`` names)."""
    return Parameter(name=str(name), value=float(value))
