"""PX4 flight modes on MAVLink: ``custom_mode`` layout, ``base_mode`` flags, state names.

PX4 packs its mode into HEARTBEAT.custom_mode (32 bits, from the low end: 16 reserved
bits, main_mode 8 bits, sub_mode 8 bits)::

    custom_mode = (sub_mode << 24) | (main_mode << 16)

so OFFBOARD = 6 << 16 = 393216 and AUTO.LAND = (6 << 24) | (4 << 16). A mode change is
COMMAND_LONG MAV_CMD_DO_SET_MODE with param1 = base mode flags (CUSTOM_MODE_ENABLED),
param2 = main mode, param3 = sub mode.

The vehicle's commander (``sitl.commander.machine``) names its states with plain strings
(``"DISARMED"``, ``"ARMED"``, ``"TAKEOFF"``, ``"OFFBOARD"``, ``"HOLD"``, ``"LAND"``,
``"RTL"``); :func:`px4_mode_for_state` and :func:`state_for_px4_mode` are the mapping
between those names and PX4 modes, so ``mavlink_bridge`` needs no import of ``sitl``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, IntFlag


class MainMode(IntEnum):
    """PX4 main modes (``PX4_CUSTOM_MAIN_MODE_*``)."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7
    RATTITUDE = 8


class AutoSubMode(IntEnum):
    """PX4 sub-modes of AUTO (``PX4_CUSTOM_SUB_MODE_AUTO_*``)."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3  # shown as "Hold"
    MISSION = 4
    RTL = 5
    LAND = 6


class BaseMode(IntFlag):
    """HEARTBEAT.base_mode bits (``MAV_MODE_FLAG_*``)."""

    CUSTOM_MODE_ENABLED = 1
    TEST_ENABLED = 2
    AUTO_ENABLED = 4
    GUIDED_ENABLED = 8
    STABILIZE_ENABLED = 16
    HIL_ENABLED = 32
    MANUAL_INPUT_ENABLED = 64
    SAFETY_ARMED = 128


def encode_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    """``custom_mode`` for a PX4 main mode and sub mode (each 0..255)."""
    if not (0 <= main_mode <= 255 and 0 <= sub_mode <= 255):
        raise ValueError(f"PX4 main/sub mode out of range: {main_mode}, {sub_mode}")
    return (sub_mode << 24) | (main_mode << 16)


def decode_custom_mode(custom_mode: int) -> tuple[int, int]:
    """``(main_mode, sub_mode)`` from a PX4 ``custom_mode``."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


@dataclass(frozen=True)
class Px4Mode:
    """A PX4 mode: main mode plus sub mode (0 when the main mode has none)."""

    main: int
    sub: int = 0

    @property
    def custom_mode(self) -> int:
        """The HEARTBEAT.custom_mode value."""
        return encode_custom_mode(self.main, self.sub)

    @classmethod
    def from_custom_mode(cls, custom_mode: int) -> Px4Mode:
        """Decode a HEARTBEAT.custom_mode."""
        return cls(*decode_custom_mode(custom_mode))

    @property
    def name(self) -> str:
        """``"OFFBOARD"``, ``"AUTO.LOITER"``, ... (``"MAIN?n"`` for unknown values)."""
        try:
            main = MainMode(self.main).name
        except ValueError:
            return f"MAIN?{self.main}.{self.sub}"
        if self.main == MainMode.AUTO:
            try:
                return f"AUTO.{AutoSubMode(self.sub).name}"
            except ValueError:
                return f"AUTO.?{self.sub}"
        return main


OFFBOARD = Px4Mode(MainMode.OFFBOARD)
AUTO_TAKEOFF = Px4Mode(MainMode.AUTO, AutoSubMode.TAKEOFF)
AUTO_LOITER = Px4Mode(MainMode.AUTO, AutoSubMode.LOITER)
AUTO_MISSION = Px4Mode(MainMode.AUTO, AutoSubMode.MISSION)
AUTO_RTL = Px4Mode(MainMode.AUTO, AutoSubMode.RTL)
AUTO_LAND = Px4Mode(MainMode.AUTO, AutoSubMode.LAND)

# Commander state name -> the PX4 mode the heartbeat reports. On the ground (disarmed or
# armed idle) PX4 usually sits in Hold (AUTO.LOITER); so do we. "TAKEOFF" comes disarmed
# too (a takeoff waiting for arming, see sitl.commander.machine): AUTO.TAKEOFF, as PX4 reports it.
_STATE_TO_PX4: dict[str, Px4Mode] = {
    "DISARMED": AUTO_LOITER,
    "ARMED": AUTO_LOITER,
    "TAKEOFF": AUTO_TAKEOFF,
    "OFFBOARD": OFFBOARD,
    "HOLD": AUTO_LOITER,
    "LAND": AUTO_LAND,
    "RTL": AUTO_RTL,
}

# A PX4 mode a client may request -> the commander state name it asks for.
_PX4_TO_STATE: dict[Px4Mode, str] = {
    OFFBOARD: "OFFBOARD",
    AUTO_TAKEOFF: "TAKEOFF",
    AUTO_LOITER: "HOLD",
    AUTO_LAND: "LAND",
    AUTO_RTL: "RTL",
}


def px4_mode_for_state(state: str) -> Px4Mode:
    """The PX4 mode reported for a commander state name (unknown names report Hold)."""
    return _STATE_TO_PX4.get(str(state), AUTO_LOITER)


def state_for_px4_mode(mode: Px4Mode) -> str | None:
    """The commander state a requested PX4 mode asks for, or None if we do not fly it."""
    return _PX4_TO_STATE.get(Px4Mode(int(mode.main), int(mode.sub)))


def base_mode_flags(armed: bool, mode: Px4Mode) -> int:
    """HEARTBEAT.base_mode as PX4 fills it: custom mode enabled, armed bit, and the
    auto/guided/stabilize bits for AUTO and OFFBOARD modes."""
    flags = BaseMode.CUSTOM_MODE_ENABLED
    if armed:
        flags |= BaseMode.SAFETY_ARMED
    if mode.main in (MainMode.AUTO, MainMode.OFFBOARD):
        flags |= BaseMode.AUTO_ENABLED | BaseMode.GUIDED_ENABLED | BaseMode.STABILIZE_ENABLED
    return int(flags)


def is_armed(base_mode: int) -> bool:
    """True if a HEARTBEAT.base_mode has SAFETY_ARMED set."""
    return bool(base_mode & BaseMode.SAFETY_ARMED)
