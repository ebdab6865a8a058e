"""The MAVLink mission protocol (mission, geofence, rally) on the vehicle's side.

Implements, for ``mission_type`` MISSION (0), FENCE (1) and RALLY (2):

* **download**: MISSION_REQUEST_LIST -> MISSION_COUNT (0 is a valid answer); then
  MISSION_REQUEST_INT -> MISSION_ITEM_INT (MISSION_REQUEST -> the legacy float
  MISSION_ITEM, as PX4 answers it); the ground station's final MISSION_ACK is counted.
  A sequence number out of range -> MISSION_ACK INVALID_SEQUENCE.
* **upload**: MISSION_COUNT -> MISSION_REQUEST_INT for item 0, 1, ... as each
  MISSION_ITEM_INT (or MISSION_ITEM) arrives, then MISSION_ACK ACCEPTED and the new list
  replaces the old one (``on_mission(mission_type, items)``). Count 0 clears at once.
  A request not answered within ``retry_timeout`` of the ``now`` passed to :meth:`poll`
  is re-sent, up to ``max_retries`` times, then the upload is cancelled
  (MISSION_ACK OPERATION_CANCELLED + STATUSTEXT). Refusals (MISSION_ACK, the old list
  kept, counted in :attr:`MissionServer.counters`): an item ahead of the expected
  sequence -> INVALID_SEQUENCE (behind: a re-send, ignored); a frame we cannot fly ->
  UNSUPPORTED_FRAME; a command not allowed for the list type -> UNSUPPORTED; latitude /
  longitude out of range or NaN -> INVALID_PARAM5_X / INVALID_PARAM6_Y, NaN altitude ->
  INVALID_PARAM7, bad fence vertex count / circle radius -> INVALID_PARAM1; a mission
  type that differs from the upload's -> ERROR; too many items -> NO_SPACE; another
  ground station uploading -> DENIED. The ground station may cancel with a MISSION_ACK.
* MISSION_CLEAR_ALL (one type or MAV_MISSION_TYPE_ALL) -> MISSION_ACK ACCEPTED;
  MISSION_SET_CURRENT / MAV_CMD_DO_SET_MISSION_CURRENT -> MISSION_CURRENT (``on_set_current``).
* progress from the node: :meth:`MissionServer.mission_current` (MISSION_CURRENT at once
  on change; the link also streams it at 1 Hz) and :meth:`MissionServer.item_reached`.

Positions: global frames (GLOBAL/_INT: altitude AMSL; RELATIVE_ALT/_INT: above home)
carry latitude/longitude in degE7; local frames (LOCAL_NED, LOCAL_ENU) carry metres x
1e4 in MISSION_ITEM_INT's integer x/y. :meth:`MissionItem.local_position` turns any of
them into a local ENU goal through :func:`mavlink_bridge.frames.geodetic_to_enu`.
No clock reads, no threads: time is the ``now`` of each call.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from mavlink_bridge import frames
from mavlink_bridge.gcs.params import LinkOps
from mavlink_bridge.transport import mavlink

M = mavlink
TYPES = (M.MAV_MISSION_TYPE_MISSION, M.MAV_MISSION_TYPE_FENCE, M.MAV_MISSION_TYPE_RALLY)
TYPE_NAMES = {0: "mission", 1: "fence", 2: "rally"}
GLOBAL_AMSL = {M.MAV_FRAME_GLOBAL, M.MAV_FRAME_GLOBAL_INT}
GLOBAL_RELATIVE = {M.MAV_FRAME_GLOBAL_RELATIVE_ALT, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT}
LOCAL = {M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_LOCAL_ENU}
POSITION_FRAMES = GLOBAL_AMSL | GLOBAL_RELATIVE | LOCAL
# Commands allowed per list type -> True if the item is a position (needs a position frame).
COMMANDS: dict[int, dict[int, bool]] = {
    M.MAV_MISSION_TYPE_MISSION: {
        M.MAV_CMD_NAV_WAYPOINT: True, M.MAV_CMD_NAV_LOITER_UNLIM: True,
        M.MAV_CMD_NAV_LOITER_TIME: True, M.MAV_CMD_NAV_LAND: True, M.MAV_CMD_NAV_TAKEOFF: True,
        M.MAV_CMD_NAV_RETURN_TO_LAUNCH: False, M.MAV_CMD_DO_CHANGE_SPEED: False},
    M.MAV_MISSION_TYPE_FENCE: {
        M.MAV_CMD_NAV_FENCE_RETURN_POINT: True, M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION: True,
        M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION: True,
        M.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION: True, M.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION: True},
    M.MAV_MISSION_TYPE_RALLY: {M.MAV_CMD_NAV_RALLY_POINT: True},
}
_POLYGON = {M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
            M.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION}
_CIRCLE = {M.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, M.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION}
Partner = Any  # opaque to this module: where the link sends replies (endpoint, address)


@dataclass(frozen=True)
class MissionItem:
    """One item as MISSION_ITEM_INT carries it (x, y: degE7 or metres x 1e4)."""

    seq: int
    frame: int
    command: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int

    @property
    def lat_lon_alt(self) -> tuple[float, float, float] | None:
        """(lat deg, lon deg, alt m) for global frames, else None."""
        if self.frame in GLOBAL_AMSL | GLOBAL_RELATIVE:
            return (self.x / 1e7, self.y / 1e7, self.z)
        return None

    def local_position(self, origin: frames.Geodetic, home: frames.Vec3 = (0.0, 0.0, 0.0)
                       ) -> frames.Vec3 | None:
        """The item's position in local ENU metres (None without one). Relative-altitude
        frames are above ``home`` (local ENU); AMSL is through ``origin``."""
        if self.frame in GLOBAL_AMSL | GLOBAL_RELATIVE:
            alt = self.z + (origin[2] + home[2] if self.frame in GLOBAL_RELATIVE else 0.0)
            return frames.geodetic_to_enu(self.x / 1e7, self.y / 1e7, alt, origin)
        if self.frame == M.MAV_FRAME_LOCAL_NED:
            return frames.ned_to_enu(self.x / 1e4, self.y / 1e4, self.z)
        if self.frame == M.MAV_FRAME_LOCAL_ENU:
            return (self.x / 1e4, self.y / 1e4, self.z)
        return None

    def to_int_message(self, target: tuple[int, int], current: bool) -> Any:
        return M.MAVLink_mission_item_int_message(
            *target, self.seq, self.frame, self.command, int(current), self.autocontinue,
            self.param1, self.param2, self.param3, self.param4, self.x, self.y, self.z,
            self.mission_type)

    def to_float_message(self, target: tuple[int, int], current: bool) -> Any:
        scale = 1e4 if self.frame in LOCAL else 1e7
        return M.MAVLink_mission_item_message(
            *target, self.seq, self.frame, self.command, int(current), self.autocontinue,
            self.param1, self.param2, self.param3, self.param4, self.x / scale,
            self.y / scale, self.z, self.mission_type)


def item_from_message(msg: Any) -> MissionItem | int:
    """A MISSION_ITEM_INT or MISSION_ITEM as a :class:`MissionItem`, or the MAV_MISSION
    error for a position we cannot represent (NaN / out-of-range x or y)."""
    x, y = msg.x, msg.y
    if msg.get_type() == "MISSION_ITEM":  # float lat/lon (or metres): to MISSION_ITEM_INT
        scale = 1e4 if msg.frame in LOCAL else 1e7
        if not math.isfinite(x) or abs(x * scale) >= 2**31:
            return M.MAV_MISSION_INVALID_PARAM5_X
        if not math.isfinite(y) or abs(y * scale) >= 2**31:
            return M.MAV_MISSION_INVALID_PARAM6_Y
        x, y = round(x * scale), round(y * scale)
    return MissionItem(msg.seq, msg.frame, msg.command, msg.autocontinue, msg.param1,
                       msg.param2, msg.param3, msg.param4, int(x), int(y), msg.z,
                       msg.mission_type)


def check_item(item: MissionItem, mission_type: int) -> int:
    """MAV_MISSION_ACCEPTED if we can fly/keep ``item`` in a ``mission_type`` list, else
    the MAV_MISSION error naming the first problem."""
    positional = COMMANDS[mission_type].get(item.command)
    if positional is None:
        return M.MAV_MISSION_UNSUPPORTED
    if not positional:
        return M.MAV_MISSION_ACCEPTED if item.frame in POSITION_FRAMES | {
            M.MAV_FRAME_MISSION} else M.MAV_MISSION_UNSUPPORTED_FRAME
    if item.frame not in POSITION_FRAMES:
        return M.MAV_MISSION_UNSUPPORTED_FRAME
    if item.frame not in LOCAL:
        if not -90e7 <= item.x <= 90e7:
            return M.MAV_MISSION_INVALID_PARAM5_X
        if not -180e7 <= item.y <= 180e7:
            return M.MAV_MISSION_INVALID_PARAM6_Y
    if not math.isfinite(item.z):
        return M.MAV_MISSION_INVALID_PARAM7
    if item.command in _POLYGON and not (math.isfinite(item.param1) and item.param1 >= 3):
        return M.MAV_MISSION_INVALID_PARAM1
    if item.command in _CIRCLE and not (math.isfinite(item.param1) and item.param1 > 0):
        return M.MAV_MISSION_INVALID_PARAM1
    return M.MAV_MISSION_ACCEPTED


@dataclass(frozen=True)
class MissionConfig:
    """Upload pacing and limits."""

    retry_timeout: float = 0.25  # s without the requested item -> request it again
    max_retries: int = 10  # then the upload is cancelled
    max_items: int = 500  # per list


@dataclass
class _Upload:
    partner: Partner
    peer: tuple[int, int]  # (system, component) of the uploading ground station
    mission_type: int
    count: int
    items: list[MissionItem]
    deadline: float
    retries: int = 0


class MissionServer:
    """The three lists, the (single) upload in progress, progress reports."""

    def __init__(self, link: LinkOps, config: MissionConfig | None = None,
                 on_mission: Callable[[int, list[MissionItem]], None] | None = None,
                 on_set_current: Callable[[int], None] | None = None) -> None:
        self.link = link
        self.config = config or MissionConfig()
        self.on_mission = on_mission
        self.on_set_current = on_set_current
        self.counters: Counter[str] = Counter()
        self.lists: dict[int, list[MissionItem]] = {t: [] for t in TYPES}
        self.current = 0
        self.state = M.MISSION_STATE_NO_MISSION
        self._upload: _Upload | None = None

    # ------------------------------------------------------------------ helpers
    def _ack(self, msg: Any, result: int, mission_type: int) -> Any:
        if result != M.MAV_MISSION_ACCEPTED:
            self.counters[f"refused.{result}"] += 1
        return M.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                             result, mission_type)

    def _request(self, up: _Upload, seq: int) -> Any:
        return M.MAVLink_mission_request_int_message(*up.peer, seq, up.mission_type)

    def current_message(self, now: float = 0.0) -> Any:
        """MISSION_CURRENT for the mission list (streamed at 1 Hz by the link)."""
        total = len(self.lists[M.MAV_MISSION_TYPE_MISSION])
        return M.MAVLink_mission_current_message(self.current, total, self.state, 0)

    def _set_list(self, mission_type: int, items: list[MissionItem]) -> None:
        self.lists[mission_type] = items
        if mission_type == M.MAV_MISSION_TYPE_MISSION:
            self.current = 0
            self.state = M.MISSION_STATE_NOT_STARTED if items else M.MISSION_STATE_NO_MISSION
            self.link.broadcast(self.current_message())
        if self.on_mission is not None:
            self.on_mission(mission_type, list(items))

    # ------------------------------------------------------------------ download
    def on_request_list(self, msg: Any, now: float, partner: Partner = None) -> list[Any]:
        if msg.mission_type not in TYPES:
            return [self._ack(msg, M.MAV_MISSION_UNSUPPORTED, msg.mission_type)]
        self.counters["download"] += 1
        return [M.MAVLink_mission_count_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                                len(self.lists[msg.mission_type]),
                                                msg.mission_type)]

    def on_request_item(self, msg: Any, now: float, partner: Partner = None) -> list[Any]:
        """MISSION_REQUEST_INT (-> MISSION_ITEM_INT) or MISSION_REQUEST (-> MISSION_ITEM)."""
        if msg.mission_type not in TYPES:
            return [self._ack(msg, M.MAV_MISSION_UNSUPPORTED, msg.mission_type)]
        items = self.lists[msg.mission_type]
        if not 0 <= msg.seq < len(items):
            return [self._ack(msg, M.MAV_MISSION_INVALID_SEQUENCE, msg.mission_type)]
        item = items[msg.seq]
        current = msg.mission_type == M.MAV_MISSION_TYPE_MISSION and msg.seq == self.current
        target = (msg.get_srcSystem(), msg.get_srcComponent())
        if msg.get_type() == "MISSION_REQUEST":
            return [item.to_float_message(target, current)]
        return [item.to_int_message(target, current)]

    def on_ack(self, msg: Any, now: float, partner: Partner = None) -> list[Any]:
        up = self._upload
        if up is not None and up.peer == (msg.get_srcSystem(), msg.get_srcComponent()) and \
                msg.mission_type == up.mission_type:
            self._upload = None  # the ground station cancelled its upload
            self.counters["upload_cancelled_by_gcs"] += 1
        else:
            self.counters["download_acked"] += 1
        return []

    # ------------------------------------------------------------------ upload
    def on_count(self, msg: Any, now: float, partner: Partner = None) -> list[Any]:
        t = msg.mission_type
        if t not in TYPES:
            return [self._ack(msg, M.MAV_MISSION_UNSUPPORTED, t)]
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        if self._upload is not None:
            if self._upload.peer != peer:
                return [self._ack(msg, M.MAV_MISSION_DENIED, t)]
            self.counters["upload_restarted"] += 1
            self._upload = None
        if msg.count > self.config.max_items:
            return [self._ack(msg, M.MAV_MISSION_NO_SPACE, t)]
        if msg.count == 0:
            self._set_list(t, [])
            self.counters["upload_ok"] += 1
            return [self._ack(msg, M.MAV_MISSION_ACCEPTED, t)]
        up = _Upload(partner, peer, t, msg.count, [], now + self.config.retry_timeout)
        self._upload = up
        return [self._request(up, 0)]

    def on_item(self, msg: Any, now: float, partner: Partner = None) -> list[Any]:
        """MISSION_ITEM_INT or MISSION_ITEM during an upload."""
        up = self._upload
        if up is None or up.peer != (msg.get_srcSystem(), msg.get_srcComponent()):
            self.counters["item_unexpected"] += 1
            return []
        if msg.mission_type != up.mission_type:
            return self._fail(msg, M.MAV_MISSION_ERROR)
        expected = len(up.items)
        if msg.seq < expected:  # a re-send of an item we have
            self.counters["item_duplicate"] += 1
            return []
        if msg.seq > expected:
            return self._fail(msg, M.MAV_MISSION_INVALID_SEQUENCE)
        item = item_from_message(msg)
        result = item if isinstance(item, int) else check_item(item, up.mission_type)
        if result != M.MAV_MISSION_ACCEPTED:
            return self._fail(msg, result)
        assert isinstance(item, MissionItem)
        up.items.append(replace(item, seq=expected))
        up.retries, up.deadline = 0, now + self.config.retry_timeout
        if len(up.items) < up.count:
            return [self._request(up, len(up.items))]
        self._upload = None
        self.counters["upload_ok"] += 1
        self._set_list(up.mission_type, up.items)
        return [self._ack(msg, M.MAV_MISSION_ACCEPTED, up.mission_type)]

    def _fail(self, msg: Any, result: int) -> list[Any]:
        up = self._upload
        assert up is not None
        self._upload = None
        self.counters["upload_failed"] += 1
        self.link.statustext(f"{TYPE_NAMES[up.mission_type]} upload refused: item "
                             f"{msg.seq} error {result}", "warning")
        return [self._ack(msg, result, up.mission_type)]

    def poll(self, now: float) -> list[tuple[Partner, Any]]:
        """Re-send an unanswered MISSION_REQUEST_INT, or give the upload up; what to send."""
        up = self._upload
        if up is None or now < up.deadline:
            return []
        if up.retries >= self.config.max_retries:
            self._upload = None
            self.counters["upload_timeout"] += 1
            self.link.statustext(f"{TYPE_NAMES[up.mission_type]} upload timed out", "warning")
            return [(up.partner, M.MAVLink_mission_ack_message(
                *up.peer, M.MAV_MISSION_OPERATION_CANCELLED, up.mission_type))]
        up.retries += 1
        up.deadline = now + self.config.retry_timeout
        self.counters["request_resent"] += 1
        return [(up.partner, self._request(up, len(up.items)))]

    # ------------------------------------------------------------------ other requests
    def on_clear_all(self, msg: Any, now: float, partner: Partner = None) -> list[Any]:
        t = msg.mission_type
        if t not in (*TYPES, M.MAV_MISSION_TYPE_ALL):
            return [self._ack(msg, M.MAV_MISSION_UNSUPPORTED, t)]
        for kind in TYPES if t == M.MAV_MISSION_TYPE_ALL else (t,):
            self._set_list(kind, [])
        self.counters["cleared"] += 1
        return [self._ack(msg, M.MAV_MISSION_ACCEPTED, t)]

    def set_current(self, seq: int) -> bool:
        """A ground station's MISSION_SET_CURRENT / DO_SET_MISSION_CURRENT: False if ``seq``
        is not an item of the mission (counted, STATUSTEXT)."""
        if not 0 <= seq < len(self.lists[M.MAV_MISSION_TYPE_MISSION]):
            self.counters["set_current_invalid"] += 1
            self.link.statustext(f"Mission set current: no item {seq}", "warning")
            return False
        self.mission_current(seq)
        if self.on_set_current is not None:
            self.on_set_current(seq)
        return True

    def on_set_current_msg(self, msg: Any, now: float, partner: Partner = None) -> list[Any]:
        self.set_current(msg.seq)
        return []

    # ------------------------------------------------------------------ progress (node)
    def mission_current(self, seq: int) -> None:
        """The node flies item ``seq`` now: MISSION_CURRENT at once if it changed."""
        changed = seq != self.current or self.state != M.MISSION_STATE_ACTIVE
        self.current = seq
        if self.lists[M.MAV_MISSION_TYPE_MISSION]:
            self.state = M.MISSION_STATE_ACTIVE
        if changed:
            self.link.broadcast(self.current_message())

    def item_reached(self, seq: int) -> None:
        """The node reached item ``seq``: MISSION_ITEM_REACHED (the last one: complete)."""
        if seq == len(self.lists[M.MAV_MISSION_TYPE_MISSION]) - 1:
            self.state = M.MISSION_STATE_COMPLETE
        self.link.broadcast(M.MAVLink_mission_item_reached_message(seq))
