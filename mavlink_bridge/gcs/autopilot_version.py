"""AUTOPILOT_VERSION: what the vehicle tells a ground station it can do.

QGroundControl's first request on connect is ``MAV_CMD_REQUEST_MESSAGE`` (512) with
param1 = 148 (AUTOPILOT_VERSION); older stacks send ``MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES``
(520). Both are answered by COMMAND_ACK, then this message (see
:mod:`mavlink_bridge.vehicle_link`). The capability bits are what skyloop implements:

* MAVLINK2 -- MAVLink 2 framing on every link;
* MISSION_INT -- MISSION_ITEM_INT / MISSION_REQUEST_INT (:mod:`mavlink_bridge.gcs.missions`);
* MISSION_FENCE, MISSION_RALLY -- the same protocol for geofence and rally points;
* PARAM_FLOAT and PARAM_ENCODE_BYTEWISE -- PARAM_VALUE carries REAL32 values as floats
  and INT32 values bytewise in the float field, as PX4 does (:mod:`mavlink_bridge.gcs.params`);
* SET_POSITION_TARGET_LOCAL_NED -- the offboard velocity setpoints;
* COMMAND_INT -- COMMAND_INT is handled like COMMAND_LONG.

``flight_sw_version`` is packed as PX4 does (major, minor, patch, type byte: 255 =
release); ``uid`` is the system id so several vehicles stay distinguishable.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

from mavlink_bridge.transport import mavlink

CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
)


def _package_version() -> tuple[int, int, int]:
    """(major, minor, patch) of the installed skyloop package (pyproject.toml's version)."""
    try:
        parts = [int("".join(c for c in p if c.isdigit()) or 0)
                 for p in version("skyloop").split(".")[:3]]
    except PackageNotFoundError:
        parts = []
    return tuple((parts + [0, 0, 0])[:3])  # type: ignore[return-value]


SKYLOOP_VERSION = _package_version()  # reported as flight_sw_version
_FIRMWARE_TYPE_RELEASE = 255


def encode_version(major: int, minor: int, patch: int, kind: int = _FIRMWARE_TYPE_RELEASE) -> int:
    """A PX4-style packed version: ``major << 24 | minor << 16 | patch << 8 | kind``."""
    return (major & 0xFF) << 24 | (minor & 0xFF) << 16 | (patch & 0xFF) << 8 | (kind & 0xFF)


def autopilot_version(system_id: int) -> object:
    """The AUTOPILOT_VERSION message of vehicle ``system_id``."""
    version = encode_version(*SKYLOOP_VERSION)
    return mavlink.MAVLink_autopilot_version_message(
        CAPABILITIES, version, version, 0, 0, bytes(8), bytes(8), bytes(8), 0, 0,
        system_id, bytes(18))
