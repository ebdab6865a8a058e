"""The vehicle's parameters: one table that the MAVLink side and the nodes share.

Ground stations read and set these through the MAVLink parameter protocol
(``mavlink_bridge.gcs.params``); the nodes that act on them (``sim``: commander and
autopilot, and the LiDAR's range for the radius; ``perception``: the icosahedron radius)
apply them when they change. Names follow PX4 where PX4 has the parameter
(``COM_OF_LOSS_T``, ``MPC_XY_VEL_MAX``, ...) and use the ``SKY_`` prefix where it does
not. Every name fits MAVLink's 16-character ``param_id``. Pure: no I/O, no Zenoh.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from bus.task import TASK, TaskSpec


@dataclass(frozen=True)
class ParamDef:
    """One parameter: name, default, closed range, MAVLink type and who applies it.

    ``sets`` names what it sets, ``"<owner>.<attribute>"`` (the node that applies it
    passes its owners to :func:`bind`); the config dataclasses take their defaults from
    here (:func:`default`), so a default exists once. ``task_field``: the
    :class:`~bus.task.TaskSpec` field it changes (what the policy sees or does); its
    default is the task's, and the policy node refuses to fly under another value.
    """

    name: str
    default: float
    minimum: float
    maximum: float
    kind: str  # "float" (MAV_PARAM_TYPE_REAL32) or "int" (MAV_PARAM_TYPE_INT32)
    unit: str
    applies_to: str  # "sim" or "perception" (the owner; ``sets`` may reach the other too)
    doc: str
    sets: tuple[str, ...] = ()
    task_field: str | None = None


PARAMS: tuple[ParamDef, ...] = (
    ParamDef("COM_OF_LOSS_T", 1.0, 0.1, 60.0, "float", "s", "sim",
             "offboard setpoint loss: this long without a setpoint -> HOLD (failsafe)",
             sets=("commander.setpoint_timeout",)),
    ParamDef("SKY_HOLD_LAND_T", 5.0, 0.0, 600.0, "float", "s", "sim",
             "failsafe HOLD lasts this long, then LAND",
             sets=("commander.hold_before_land",)),
    ParamDef("MPC_XY_VEL_MAX", TASK.max_speed_xy, 0.1, 20.0, "float", "m/s", "sim",
             "maximum horizontal speed the autopilot flies; limits each horizontal axis "
             "(the env's box action space), PX4 limits the norm",
             sets=("autopilot.max_speed_xy", "commander.rtl_speed"),
             task_field="max_speed_xy"),
    ParamDef("MPC_Z_VEL_MAX", TASK.max_speed_z, 0.1, 10.0, "float", "m/s", "sim",
             "maximum vertical speed the autopilot flies (up and down)",
             sets=("autopilot.max_speed_z", "commander.rtl_climb_speed"),
             task_field="max_speed_z"),
    ParamDef("MIS_TAKEOFF_ALT", 2.5, 0.5, 100.0, "float", "m", "sim",
             "takeoff altitude above the takeoff point when NAV_TAKEOFF gives none (NaN: "
             "MAVSDK's takeoff; its set_takeoff_altitude sets this)",
             sets=("commander.takeoff_altitude",)),
    ParamDef("GF_MAX_HOR_DIST", 60.0, 0.0, 10000.0, "float", "m", "sim",
             "geofence: horizontal distance from home beyond which RTL (0: off)",
             sets=("commander.geofence",)),
    ParamDef("SKY_FLIGHT_LVL", 3.5, 0.5, 100.0, "float", "m", "sim",
             "flight level above ground for RTL and goals from the ground station",
             sets=("commander.flight_level",)),
    ParamDef("SKY_ICO_RADIUS", TASK.ico_radius, 0.5, 50.0, "float", "m", "perception",
             "truncated-icosahedron radius p_radius of the observation (eq. 3.1)",
             sets=("observation.radius", "lidar.ico_radius"), task_field="ico_radius"),
)

BY_NAME: dict[str, ParamDef] = {p.name: p for p in PARAMS}
assert all(len(p.name) <= 16 for p in PARAMS)
assert all(p.default == getattr(TASK, p.task_field) for p in PARAMS if p.task_field)


def default(name: str) -> float:
    """The default of parameter ``name`` (the one place it is written)."""
    return BY_NAME[name].default


def bind(name: str, value: float, owners: Mapping[str, object | None]) -> bool:
    """Set what parameter ``name`` sets (``ParamDef.sets``) on the ``owners`` given by
    name (None: not present, skipped); True if it sets something of theirs."""
    hit = False
    for target in BY_NAME[name].sets if name in BY_NAME else ():
        owner, attribute = target.split(".")
        if owner in owners:
            hit = True
            if owners[owner] is not None:
                setattr(owners[owner], attribute, value)
    return hit


def off_task(task: TaskSpec, name: str, value: float) -> str | None:
    """Why ``value`` of ``name`` is not what ``task`` was trained under, or None (also
    for parameters the task does not depend on)."""
    p = BY_NAME.get(name)
    if p is None or p.task_field is None:
        return None
    trained = float(getattr(task, p.task_field))
    if math.isclose(float(value), trained, rel_tol=1e-6):
        return None
    return f"{name}={float(value):g} {p.unit}, trained with {trained:g}"


def defaults() -> dict[str, float]:
    """Every parameter at its default."""
    return {p.name: p.default for p in PARAMS}


def check(name: str, value: float) -> float:
    """``value`` for parameter ``name`` if valid (ints rounded exactly), else ValueError
    naming the parameter and the problem."""
    p = BY_NAME.get(name)
    if p is None:
        raise ValueError(f"unknown parameter {name!r}; known: {sorted(BY_NAME)}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: {value!r} is not a number") from None
    if not math.isfinite(v):
        raise ValueError(f"{name}: {v} is not finite")
    if p.kind == "int":
        if v != int(v):
            raise ValueError(f"{name}: {v} is not an integer")
        v = float(int(v))
    if not p.minimum <= v <= p.maximum:
        raise ValueError(f"{name}: {v:g} outside [{p.minimum:g}, {p.maximum:g}] {p.unit}")
    return v
