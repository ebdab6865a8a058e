"""Zenoh key expressions and the table of topics: the one place that spells them.

Every key is ``skyloop/<vehicle>/<topic>``; the same name with a leading slash is the
ROS 2 topic (``/skyloop/uav1/lidar/points``), which is what the MCAP log and a
Zenoh-ROS 2 bridge show. No other package builds a key string by hand: use
:func:`key`, :func:`key_all` and :func:`parse_key`.

This module is pure (no Zenoh import); :mod:`bus.session` maps ``Topic.congestion`` to
Zenoh's ``CongestionControl``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

PREFIX = "skyloop"
#: Vehicle names: a key-expression chunk without wildcards or separators.
_VEHICLE_RE = re.compile(r"^[A-Za-z0-9_\-]+$")

# Topic names (the part after ``skyloop/<vehicle>/``).
LIDAR_POINTS = "lidar/points"
ODOM = "odom"
TRUTH = "truth"
CMD_VEL = "cmd_vel"
GOAL = "goal"
OBSERVATION = "observation"
EPISODE = "episode"
CLOCK = "clock"
ACTOR = "actor"
STATUS = "status"
PARAMS = "params"
COMMAND = "command"
STEP_RECORD = "step_record"


@dataclass(frozen=True)
class Topic:
    """One topic of the bus.

    ``congestion`` is ``"block"`` (the publisher waits rather than dropping; used for
    every topic by default because lockstep and the log need every message and large
    payloads are lost silently otherwise) or ``"drop"``. ``express`` sends without
    batching; it is off for every topic so that the messages one session publishes
    reach a subscriber in publish order across topics (an express message can overtake
    a batched one, e.g. a step's command overtaking the episode's END event).
    """

    name: str
    msgtype: str
    doc: str
    congestion: str = "block"
    express: bool = False


TOPICS: dict[str, Topic] = {
    t.name: t
    for t in (
        Topic(LIDAR_POINTS, "sensor_msgs/msg/PointCloud2",
              "VLP-16 scan in the sensor frame: x/y/z, intensity float32, ring uint16"),
        Topic(ODOM, "nav_msgs/msg/Odometry",
              "estimated state (pose and velocity in world ENU)"),
        Topic(TRUTH, "nav_msgs/msg/Odometry",
              "ground-truth state (pose and velocity in world ENU)"),
        Topic(CMD_VEL, "skyloop_msgs/msg/VelocitySetpoint",
              "velocity setpoint: frame (body or world), velocity, yaw rate or heading; "
              "stamp = the step it answers"),
        Topic(GOAL, "geometry_msgs/msg/PoseStamped", "navigation goal, world ENU"),
        Topic(OBSERVATION, "skyloop_msgs/msg/Observation",
              "perception output (35 attributes, or 3 x 35 stacked)"),
        Topic(EPISODE, "skyloop_msgs/msg/EpisodeEvent",
              "episode start (seed, start, goal) and end (outcome, steps)"),
        Topic(CLOCK, "skyloop_msgs/msg/StepClock",
              "lockstep step clock (step index, sim time)"),
        Topic(ACTOR, "skyloop_msgs/msg/ActorWeights",
              "actor weights blob + version (actor-learner)"),
        Topic(STATUS, "skyloop_msgs/msg/VehicleStatus",
              "the commander's state and events (sim -> bridge: heartbeat, STATUSTEXT)"),
        Topic(PARAMS, "skyloop_msgs/msg/Parameter",
              "a vehicle parameter set (bus.params names), applied by the sim"),
        Topic(COMMAND, "skyloop_msgs/msg/VehicleCommand",
              "commander requests: a Zenoh query answered by the sim with CommandAck"),
        Topic(STEP_RECORD, "skyloop_msgs/msg/StepRecord",
              "the episode core's record of each step: D_pre, D_cur, altitude, h, g, "
              "collision, outcome (what eq. 3.5 and the outcome derive from)"),
    )
}


def topic_info(topic: str) -> Topic:
    """The table entry of ``topic``; ``KeyError`` with the known names if unknown."""
    try:
        return TOPICS[topic]
    except KeyError:
        raise KeyError(f"unknown topic {topic!r}; known: {sorted(TOPICS)}") from None


def msgtype(topic: str) -> str:
    """ROS 2 message type name of ``topic`` (e.g. ``'nav_msgs/msg/Odometry'``)."""
    return topic_info(topic).msgtype


def check_vehicle(vehicle: str, *, wildcard: bool = False) -> str:
    """Validate a vehicle name (``'*'`` allowed only with ``wildcard``); return it."""
    if wildcard and vehicle == "*":
        return vehicle
    if not isinstance(vehicle, str) or not _VEHICLE_RE.match(vehicle):
        raise ValueError(
            f"vehicle must match {_VEHICLE_RE.pattern} (no '/', '*', '$', '?', '#'), "
            f"got {vehicle!r}"
        )
    return vehicle


def key(vehicle: str, topic: str, *, wildcard: bool = False) -> str:
    """Key expression ``skyloop/<vehicle>/<topic>``.

    ``wildcard=True`` allows ``vehicle='*'`` (every vehicle; for subscribers).
    """
    check_vehicle(vehicle, wildcard=wildcard)
    topic_info(topic)
    return f"{PREFIX}/{vehicle}/{topic}"


#: Readiness is not a topic: a node that is up holds the Zenoh liveliness token
#: ``skyloop/<vehicle>/ready/<node>`` (gone when it closes or dies).
READY = "ready"
#: the vehicle part of a readiness key of a node that serves every vehicle (a recorder)
ANY_VEHICLE = "_"
_NODE_RE = re.compile(r"^[a-z][a-z0-9_]*$")


def ready_key(vehicle: str, node: str = "*") -> str:
    """Key of node ``node``'s readiness token (``node='*'``: every node's, to watch)."""
    check_vehicle(vehicle, wildcard=True)
    if node != "*" and not _NODE_RE.match(node):
        raise ValueError(f"bad node name {node!r}")
    return f"{PREFIX}/{vehicle}/{READY}/{node}"


def key_all(vehicle: str | None = None) -> str:
    """Key expression of every topic: of one vehicle, or of all (``skyloop/**``)."""
    if vehicle is None:
        return f"{PREFIX}/**"
    return f"{PREFIX}/{check_vehicle(vehicle)}/**"


def parse_key(key_expr: str) -> tuple[str, str]:
    """``'skyloop/uav1/lidar/points'`` -> ``('uav1', 'lidar/points')``.

    Raises ``ValueError`` if the key is not a concrete skyloop key of a known topic.
    """
    parts = str(key_expr).split("/", 2)
    if len(parts) != 3 or parts[0] != PREFIX:
        raise ValueError(f"not a {PREFIX}/<vehicle>/<topic> key: {key_expr!r}")
    _, vehicle, topic = parts
    if topic not in TOPICS:
        raise ValueError(f"unknown topic {topic!r} in key {key_expr!r}")
    check_vehicle(vehicle)
    return vehicle, topic


def ros_topic(vehicle: str, topic: str) -> str:
    """ROS 2 topic name of a key: ``/skyloop/<vehicle>/<topic>``."""
    return "/" + key(vehicle, topic)


def parse_ros_topic(name: str) -> tuple[str, str]:
    """``'/skyloop/uav1/odom'`` -> ``('uav1', 'odom')`` (``ValueError`` if not ours)."""
    if not name.startswith("/"):
        raise ValueError(f"ROS 2 topic names start with '/': {name!r}")
    return parse_key(name[1:])
