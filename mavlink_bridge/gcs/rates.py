"""Per-link message rates: PX4-like defaults, MAV_CMD_SET/GET_MESSAGE_INTERVAL.

Each link (api, gcs) has its own :class:`MessageRates`, as each PX4 MAVLink instance
has its own streams: SET_MESSAGE_INTERVAL (511) changes the rate on the link the command
came in on. param2 of 511: interval in microseconds, ``-1`` disables the stream, ``0``
restores the default. GET_MESSAGE_INTERVAL (510) answers MESSAGE_INTERVAL with the
current interval (``-1`` when disabled).

Scheduling runs on the ``now`` passed in (no clock reads): a due message is sent and its
next time is ``previous + interval`` (so over a span T at a poll period dt the count is
T / interval +- 1 whenever interval >= dt), or ``now + interval`` after a gap. A message
whose builder has nothing to send yet (no telemetry) stays due.

Default rates (Hz), PX4's "normal" GCS profile, rounded, with the existing
``VehicleLinkConfig`` periods for HEARTBEAT and LOCAL_POSITION_NED/ATTITUDE:

=====================  =====  =====================  =====
HEARTBEAT              1      GLOBAL_POSITION_INT    5
SYS_STATUS             1      VFR_HUD                4
EXTENDED_SYS_STATE     1      ATTITUDE               10
GPS_RAW_INT            1      ATTITUDE_QUATERNION    10
HOME_POSITION          0.5    LOCAL_POSITION_NED     10
BATTERY_STATUS         0.5    MISSION_CURRENT        1
=====================  =====  =====================  =====
"""

from __future__ import annotations

import math

from mavlink_bridge.transport import mavlink as M

EPS = 1e-9  # s: sums of control periods are not exact
DEFAULT_HZ: dict[int, float] = {  # in this order within a poll
    M.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 10.0,
    M.MAVLINK_MSG_ID_ATTITUDE: 10.0,
    M.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    M.MAVLINK_MSG_ID_GPS_RAW_INT: 1.0,
    M.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    M.MAVLINK_MSG_ID_BATTERY_STATUS: 0.5,
    M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
    M.MAVLINK_MSG_ID_VFR_HUD: 4.0,
    M.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 10.0,
    M.MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
}


def default_intervals(heartbeat_period: float, telemetry_period: float) -> dict[int, float]:
    """Default interval (s) per message id, with the link config's two periods."""
    out = {mid: 1.0 / hz for mid, hz in DEFAULT_HZ.items()}
    out[M.MAVLINK_MSG_ID_HEARTBEAT] = heartbeat_period
    out[M.MAVLINK_MSG_ID_LOCAL_POSITION_NED] = telemetry_period
    out[M.MAVLINK_MSG_ID_ATTITUDE] = telemetry_period
    return out


class MessageRates:
    """Intervals and next send times of one link's streams."""

    def __init__(self, defaults: dict[int, float]) -> None:
        self.defaults = dict(defaults)
        self.intervals: dict[int, float] = dict(defaults)  # absent: not streamed
        self._next: dict[int, float] = {}

    def due(self, now: float) -> list[int]:
        """Message ids due at ``now`` (call :meth:`sent` for those actually sent)."""
        return [mid for mid in self.intervals if now + EPS >= self._next.get(mid, -math.inf)]

    def sent(self, msg_id: int, now: float) -> None:
        """``msg_id`` went out at ``now``: schedule the next one."""
        interval = self.intervals.get(msg_id)
        if interval is None:
            return
        nxt = self._next.get(msg_id, -math.inf) + interval
        self._next[msg_id] = nxt if nxt + EPS >= now else now + interval

    def force(self, msg_id: int) -> None:
        """Send ``msg_id`` at the next :meth:`due` (e.g. a heartbeat on a mode change)."""
        if msg_id in self.intervals:
            self._next[msg_id] = -math.inf

    def set_interval(self, msg_id: int, interval_us: float) -> bool:
        """SET_MESSAGE_INTERVAL semantics; False for a value that means nothing."""
        if not math.isfinite(interval_us) or (interval_us < 0 and interval_us != -1):
            return False
        if interval_us == -1:
            self.intervals.pop(msg_id, None)
        elif interval_us == 0:
            if msg_id in self.defaults:
                self.intervals[msg_id] = self.defaults[msg_id]
            else:
                self.intervals.pop(msg_id, None)
        else:
            self.intervals[msg_id] = interval_us / 1e6
        self._next.pop(msg_id, None)  # start over: first one at the next poll
        return True

    def interval_us(self, msg_id: int) -> int:
        """MESSAGE_INTERVAL.interval_us: the interval, or -1 when not streamed."""
        interval = self.intervals.get(msg_id)
        return -1 if interval is None else int(round(interval * 1e6))
