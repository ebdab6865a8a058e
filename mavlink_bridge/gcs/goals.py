"""Goals from the ground station (issue 5 §2): missions, DO_REPOSITION and
SET_POSITION_TARGET_GLOBAL_INT become goals for the policy on the bus.

The trained policy flies in OFFBOARD; what it flies toward is the goal of the sim's
episode, and a PoseStamped on ``skyloop/<vehicle>/goal`` (world ENU) replaces it (the
running episode ends ``aborted``, the next starts where the vehicle is). So "fly a
mission" here means: send the mission's goals to the policy one after another.

* **Mission**: an uploaded MAV_MISSION_TYPE_MISSION list (:mod:`mavlink_bridge.gcs.missions`)
  is flown on MAV_CMD_MISSION_START (300; param1 = first item, else the current one) or
  on DO_SET_MODE AUTO.MISSION (what QGroundControl, MAVSDK and MAVProxy send; resumes at
  the current item). The vehicle keeps reporting OFFBOARD (the policy flies the goals;
  there is no autopilot mission mode). NAV_WAYPOINT and NAV_LOITER_* items are goals;
  NAV_TAKEOFF and DO_CHANGE_SPEED are passed (reached at once: the vehicle is already
  flying, the policy sets its own speed); NAV_LAND and NAV_RETURN_TO_LAUNCH ask the
  commander to land / return and end the mission. Item ``seq`` is sent when the previous
  one's episode ended ``success``: MISSION_CURRENT(seq) when it is sent,
  MISSION_ITEM_REACHED(seq) at the success, "Mission complete" after the last. An
  episode ending otherwise (collision, timeout, a goal from elsewhere: ``aborted``)
  stops the mission (STATUSTEXT). DO_SET_MODE to HOLD, LAND, RTL or TAKEOFF pauses it
  (AUTO.MISSION resumes); a new upload or a single goal replaces it; MISSION_SET_CURRENT
  while it runs jumps there.
* **Single goal**: MAV_CMD_DO_REPOSITION (192; COMMAND_LONG: param5/6 lat/lon degrees as
  float32, ~0.5 m, param7 AMSL; COMMAND_INT, as QGroundControl: degE7, z in its frame)
  and SET_POSITION_TARGET_GLOBAL_INT (a mask using x and y) send one goal and end a
  running mission. The same target again in OFFBOARD is not re-sent (``goal.repeat``).

**Accepted only** while the vehicle is armed, in the air and in HOLD or OFFBOARD
(otherwise DENIED, STATUSTEXT). **Refused** (DENIED and counted ``goal.rejected.<why>``,
nothing published, never an exception): latitude/longitude NaN or out of range
(``bad_latitude``/``bad_longitude``), a frame without a global position
(``unsupported_frame``), a type mask without x/y (``no_position``), a horizontal distance
from home beyond GF_MAX_HOR_DIST (``beyond_geofence``), no home/position yet
(TEMPORARILY_REJECTED, ``no_position_yet``). SET_POSITION_TARGET_GLOBAL_INT has no ACK:
its refusals are only counted (and logged).

**Positions** (one conversion: :meth:`MissionItem.local_position` via
:func:`goal_position`): AMSL frames through the link's geodetic origin, relative-altitude
frames above home (HOME_POSITION), local frames as they are. **Altitude**: as given;
NaN (DO_REPOSITION) or ignored by the type mask = the vehicle's current altitude; 0 in a
relative or local frame (the ground under home: no place to fly to) = the flight level,
SKY_FLIGHT_LVL metres above the terrain datum (local z = 0, the scenario's datum, where
the policy was trained to fly: its observation holds the goal's direction, not its
height). The bridge does not know the terrain; the sim refuses a goal below the terrain,
inside an obstacle or higher than its episodes can reach (STATUSTEXT from the sim).

Progress comes from the sim's episode events (:meth:`GoalService.on_episode`): the START
whose goal is the one sent names the episode; that episode's END decides.
The pure part (:func:`goal_position`, :func:`plan_mission`, :class:`GoalQueue`) has no
I/O; :class:`GoalService` binds it to a :class:`~mavlink_bridge.vehicle_link.VehicleLink`
and a ``publish(position)`` callable.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from bus import messages as bm
from mavlink_bridge import frames
from mavlink_bridge.gcs.missions import GLOBAL_AMSL, GLOBAL_RELATIVE, LOCAL, MissionItem, check_item
from mavlink_bridge.modes import AutoSubMode, MainMode, Px4Mode, state_for_px4_mode
from mavlink_bridge.transport import mavlink

if TYPE_CHECKING:
    from mavlink_bridge.vehicle_link import VehicleLink

log = logging.getLogger(__name__)
M = mavlink
GOAL_COMMANDS = {M.MAV_CMD_NAV_WAYPOINT, M.MAV_CMD_NAV_LOITER_UNLIM, M.MAV_CMD_NAV_LOITER_TIME}
PASSED_COMMANDS = {M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_DO_CHANGE_SPEED}
ENDING_COMMANDS = {M.MAV_CMD_NAV_LAND: "land", M.MAV_CMD_NAV_RETURN_TO_LAUNCH: "rtl"}
FLYING_STATES = ("OFFBOARD", "HOLD")
MASK_X_Y = 0b11  # POSITION_TARGET_TYPEMASK_X_IGNORE | Y_IGNORE
MASK_Z = 0b100
SAME_GOAL_M = 0.01  # a START's goal within this (horizontally) of the one sent is it
_REASONS = {M.MAV_MISSION_INVALID_PARAM5_X: "bad_latitude",
            M.MAV_MISSION_INVALID_PARAM6_Y: "bad_longitude",
            M.MAV_MISSION_INVALID_PARAM7: "bad_altitude",
            M.MAV_MISSION_UNSUPPORTED_FRAME: "unsupported_frame"}


@dataclass(frozen=True)
class Goal:
    """One thing to do: ``kind`` "goal" (fly to ``position``, local ENU), "land", "rtl"
    or "pass"; ``seq`` is the mission item (None: a single goal)."""

    kind: str
    position: frames.Vec3 | None = None
    seq: int | None = None


@dataclass(frozen=True)
class GoalFrame:
    """What turning a global position into a goal needs (see the module docstring)."""

    origin: frames.Geodetic
    home: frames.Vec3  # local ENU
    flight_level: float  # m above the datum (local z) for an altitude of 0
    geofence: float  # m from home, 0: off


def goal_position(item: MissionItem, frame: GoalFrame, current_z: float | None = None
                  ) -> frames.Vec3 | str:
    """The local ENU goal of a position ``item`` or the reason it is refused. A NaN
    altitude means ``current_z`` if that is given (else ``bad_altitude``)."""
    keep = not math.isfinite(item.z) and current_z is not None
    if keep:
        item = replace(item, z=0.0)
    result = check_item(item, M.MAV_MISSION_TYPE_MISSION)
    if result != M.MAV_MISSION_ACCEPTED:
        return _REASONS.get(result, f"mission_error_{result}")
    pos = item.local_position(frame.origin, frame.home)
    if pos is None:
        return "unsupported_frame"
    x, y, z = pos
    if keep:
        z = float(current_z)  # type: ignore[arg-type]
    elif item.z == 0.0 and item.frame in GLOBAL_RELATIVE | LOCAL:
        z = frame.flight_level
    if not all(math.isfinite(v) for v in (x, y, z)):
        return "bad_position"
    if frame.geofence > 0 and math.hypot(x - frame.home[0], y - frame.home[1]) > frame.geofence:
        return "beyond_geofence"
    return (x, y, z)


def plan_mission(items: list[MissionItem], frame: GoalFrame) -> list[Goal] | tuple[int, str]:
    """A mission's items as goals, or ``(seq, reason)`` of the first one refused."""
    plan: list[Goal] = []
    for it in items:
        if it.command in GOAL_COMMANDS:
            pos = goal_position(it, frame)
            if isinstance(pos, str):
                return (it.seq, pos)
            plan.append(Goal("goal", pos, it.seq))
        elif it.command in ENDING_COMMANDS:
            plan.append(Goal(ENDING_COMMANDS[it.command], None, it.seq))
        elif it.command in PASSED_COMMANDS:
            plan.append(Goal("pass", None, it.seq))
        else:
            return (it.seq, "unsupported_command")
    return plan


Event = tuple[str, Goal | None]  # ("goal"|"land"|"rtl"|"current"|"reached"|"done"|"failed:<o>")


class GoalQueue:
    """Which goal is flying and what comes next (pure: events in, events out)."""

    def __init__(self) -> None:
        self.plan: list[Goal] = []
        self.index = 0  # plan index of the mission item flying
        self.running = False  # a mission is being flown
        self.active: Goal | None = None  # the goal last sent, until its episode ends
        self.episode: int | None = None  # the sim's episode flying it

    def start(self, plan: list[Goal], first_seq: int = 0) -> list[Event]:
        """Fly ``plan`` from the item ``first_seq`` on (an unknown seq: from the start)."""
        self.plan = plan
        self.index = next((i for i, g in enumerate(plan) if g.seq == first_seq), 0)
        self.running = True
        return self._advance()

    def single(self, position: frames.Vec3) -> list[Event]:
        """One goal; a running mission ends."""
        self.running = False
        self.active, self.episode = Goal("goal", position), None
        return [("goal", self.active)]

    def is_active(self, position: frames.Vec3) -> bool:
        """Whether ``position`` is the goal being flown (a repeat)."""
        a = self.active
        return a is not None and a.position is not None and \
            math.dist(a.position, position) < SAME_GOAL_M

    def on_start(self, episode: int, goal_xy: tuple[float, float]) -> None:
        """An episode started toward ``goal_xy``: ours if it is the goal sent."""
        a = self.active
        if a is not None and a.position is not None and self.episode is None and \
                math.hypot(a.position[0] - goal_xy[0], a.position[1] - goal_xy[1]) < SAME_GOAL_M:
            self.episode = episode

    def on_end(self, episode: int, outcome: str) -> list[Event]:
        """An episode ended: progress if it was ours."""
        g = self.active
        if g is None or episode != self.episode:
            return []
        self.active, self.episode = None, None
        if outcome != "success":
            self.running = False
            return [(f"failed:{outcome}", g)]
        out: list[Event] = [("reached", g)]
        if self.running and g.seq is not None:
            self.index += 1
            out += self._advance()
        return out

    def _advance(self) -> list[Event]:
        out: list[Event] = []
        while self.index < len(self.plan):
            g = self.plan[self.index]
            out.append(("current", g))
            if g.kind == "goal":
                self.active, self.episode = g, None
                out.append(("goal", g))
                return out
            out += [(g.kind, g), ("reached", g)]
            self.index += 1
            if g.kind != "pass":  # land / rtl: the flight ends here
                self.running = False
                return out
        self.running = False
        out.append(("done", None))
        return out


class GoalService:
    """Binds a :class:`GoalQueue` to a vehicle link (see the module docstring)."""

    def __init__(self, link: VehicleLink, publish: Callable[[frames.Vec3], None]) -> None:
        self.link, self.publish = link, publish
        self.queue = GoalQueue()
        self.counters: Counter[str] = Counter()

    def install(self) -> None:
        """Register the commands, SET_POSITION_TARGET_GLOBAL_INT and mission callbacks."""
        link, mi = self.link, self.link.missions
        set_mode = link.commands[M.MAV_CMD_DO_SET_MODE]
        link.commands.update({
            M.MAV_CMD_MISSION_START: lambda msg, now: self._start(msg.param1, now),
            M.MAV_CMD_DO_REPOSITION: self._cmd_reposition,
            M.MAV_CMD_DO_SET_MODE: lambda msg, now: self._cmd_set_mode(set_mode, msg, now),
        })
        link.handlers["SET_POSITION_TARGET_GLOBAL_INT"] = self._on_target_global
        uploaded, jumped = mi.on_mission, mi.on_set_current

        def on_mission(mission_type: int, items: list[MissionItem]) -> None:
            if mission_type == M.MAV_MISSION_TYPE_MISSION and self.queue.running:
                self.queue.running = False
                link.statustext("Mission replaced by an upload: stopped", "warning")
            if uploaded is not None:
                uploaded(mission_type, items)

        def on_set_current(seq: int) -> None:
            if self.queue.running:
                self._start(float(seq), None)
            if jumped is not None:
                jumped(seq)

        mi.on_mission, mi.on_set_current = on_mission, on_set_current

    # ------------------------------------------------------------------ helpers
    def _frame(self) -> GoalFrame | None:
        home = self.link.reporter.home
        if home is None:
            return None
        values = self.link.params.values
        return GoalFrame(self.link.config.origin, home, values["SKY_FLIGHT_LVL"],
                         values["GF_MAX_HOR_DIST"])

    def _flying(self) -> bool:
        c = self.link.commander
        return c.armed and not c.landed and str(c.state) in FLYING_STATES

    def _refuse(self, reason: str, what: str, text: bool = True) -> int:
        self.counters[f"goal.rejected.{reason}"] += 1
        log.warning("%s refused: %s", what, reason)
        if text:
            self.link.statustext(f"{what} denied: {reason}", "warning")
        if reason == "no_position_yet":
            return M.MAV_RESULT_TEMPORARILY_REJECTED
        return M.MAV_RESULT_DENIED

    def _run(self, events: list[Event], now: float | None) -> None:
        """Carry out what the queue decided."""
        mi, link = self.link.missions, self.link
        for what, g in events:
            if what == "goal" and g is not None and g.position is not None:
                self.publish(g.position)
                self.counters["goal.published"] += 1
                x, y, z = g.position
                name = "Goal" if g.seq is None else f"Item {g.seq}"
                link.statustext(f"{name}: flying to {x:.1f} {y:.1f} {z:.1f}")
            elif what == "current" and g is not None and g.seq is not None:
                mi.mission_current(g.seq)
            elif what == "reached" and g is not None:
                if g.seq is None:
                    link.statustext("Goal reached")
                else:
                    mi.item_reached(g.seq)
            elif what in ("land", "rtl"):
                c = link.commander
                t = 0.0 if now is None else now
                verdict = c.land(t) if what == "land" else c.return_home(t)
                self.counters[f"mission.{what}.{'ok' if verdict.accepted else 'refused'}"] += 1
            elif what == "done":
                link.statustext("Mission complete")
            elif what.startswith("failed:"):
                self.counters[f"goal.{what.replace(':', '.')}"] += 1
                name = "goal" if g is None or g.seq is None else f"item {g.seq}"
                link.statustext(f"Mission stopped: {name} {what[7:]}", "warning")

    # ------------------------------------------------------------------ missions
    def _start(self, first: float, now: float | None) -> int:
        mi = self.link.missions
        items = mi.lists[M.MAV_MISSION_TYPE_MISSION]
        if not items:
            return self._refuse("no_mission", "Mission start")
        if not self._flying():
            return self._refuse("not_flying", "Mission start")
        frame = self._frame()
        if frame is None:
            return self._refuse("no_position_yet", "Mission start")
        plan = plan_mission(items, frame)
        if isinstance(plan, tuple):
            return self._refuse(f"item_{plan[0]}_{plan[1]}"[:30], "Mission start")
        seq = int(first) if math.isfinite(first) and 0 <= first < len(items) else mi.current
        self.counters["mission.started"] += 1
        self._run(self.queue.start(plan, seq), now)
        return M.MAV_RESULT_ACCEPTED

    def _cmd_set_mode(self, set_mode: Callable[[Any, float], int], msg: Any, now: float) -> int:
        p = (msg.param1, msg.param2, msg.param3)
        whole = all(math.isfinite(v) and v == int(v) and 0 <= v <= 255 for v in p)
        if whole and p[1:] == (MainMode.AUTO, AutoSubMode.MISSION) and int(p[0]) & 1:
            return self._start(math.nan, now)
        result = set_mode(msg, now)
        asked = state_for_px4_mode(Px4Mode(int(p[1]), int(p[2]))) if whole else None
        if result == M.MAV_RESULT_ACCEPTED and asked not in (None, "OFFBOARD") and \
                self.queue.running:
            self.queue.running = False
            self.link.missions.state = M.MISSION_STATE_PAUSED
            self.link.broadcast(self.link.missions.current_message())
            self.link.statustext("Mission paused")
        return result

    # ------------------------------------------------------------------ single goals
    def _single(self, item: MissionItem, current: bool, what: str, text: bool) -> int:
        if not self._flying():
            return self._refuse("not_flying", what, text)
        frame = self._frame()
        telemetry = self.link.reporter.telemetry
        if frame is None or telemetry is None:
            return self._refuse("no_position_yet", what, text)
        pos = goal_position(item, frame, telemetry.position[2] if current else None)
        if isinstance(pos, str):
            return self._refuse(pos, what, text)
        if self.queue.is_active(pos) and str(self.link.commander.state) == "OFFBOARD":
            self.counters["goal.repeat"] += 1
            return M.MAV_RESULT_ACCEPTED
        self.counters["goal.accepted"] += 1
        self._run(self.queue.single(pos), None)
        return M.MAV_RESULT_ACCEPTED

    def _cmd_reposition(self, msg: Any, now: float) -> int:
        """DO_REPOSITION, COMMAND_LONG (degrees, AMSL) or COMMAND_INT (degE7, its frame)."""
        frame = getattr(msg, "frame", None)
        if frame is None:  # COMMAND_LONG: degrees as floats
            for value, reason in ((msg.param5, "bad_latitude"), (msg.param6, "bad_longitude")):
                if not (math.isfinite(value) and abs(value) <= 180.0):
                    return self._refuse(reason, "Reposition")
            frame, x, y = M.MAV_FRAME_GLOBAL, round(msg.param5 * 1e7), round(msg.param6 * 1e7)
        else:
            x, y = int(msg.param5), int(msg.param6)
            if frame not in GLOBAL_AMSL | GLOBAL_RELATIVE:
                return self._refuse("unsupported_frame", "Reposition")
        item = MissionItem(0, frame, M.MAV_CMD_NAV_WAYPOINT, 1, 0.0, 0.0, 0.0, 0.0, x, y,
                           float(msg.param7), M.MAV_MISSION_TYPE_MISSION)
        return self._single(item, math.isnan(msg.param7), "Reposition", True)

    def _on_target_global(self, ep: Any, msg: Any, addr: Any, now: float) -> None:
        c = self.link.config
        if msg.target_system != c.system_id or msg.target_component not in (0, c.component_id):
            self.counters["target_global.other_target"] += 1
            return
        if msg.type_mask & MASK_X_Y:
            self._refuse("no_position", "Target", text=False)
            return
        if msg.coordinate_frame not in GLOBAL_AMSL | GLOBAL_RELATIVE:
            self._refuse("unsupported_frame", "Target", text=False)
            return
        keep = bool(msg.type_mask & MASK_Z) or not math.isfinite(msg.alt)
        item = MissionItem(0, msg.coordinate_frame, M.MAV_CMD_NAV_WAYPOINT, 1, 0.0, 0.0, 0.0,
                           0.0, int(msg.lat_int), int(msg.lon_int),
                           math.nan if keep else float(msg.alt), M.MAV_MISSION_TYPE_MISSION)
        self._single(item, keep, "Target", text=False)

    # ------------------------------------------------------------------ the sim's episodes
    def on_episode(self, msg: Any, now: float | None = None) -> None:
        """An ``EpisodeEvent`` from the bus (START: which episode flies our goal; END:
        progress)."""
        if int(msg.event) == bm.START:
            self.queue.on_start(int(msg.episode), (float(msg.goal.x), float(msg.goal.y)))
        elif int(msg.event) == bm.END:
            self._run(self.queue.on_end(int(msg.episode), bm.outcome_name(msg)), now)
