"""What the MAVLink side exchanges with the rest of skyloop (all in skyloop's frames).

The bridge is glued to the vehicle by three small things, so that the same link code
runs in-process (tests, a single-process sim) and later behind Zenoh:

* :class:`VelocityCommand` -- what a valid ``SET_POSITION_TARGET_LOCAL_NED`` becomes
  (out of the bridge: a callback, later a bus publisher);
* :class:`VehicleTelemetry` -- the vehicle state the bridge reports, in ENU/FLU (into the
  bridge: ``VehicleLink.update_telemetry``, later a bus subscriber);
* :class:`CommanderLike` -- the vehicle's commander as the bridge sees it: arm, disarm,
  takeoff, land, set mode (RTL included), each answered with a :class:`Verdict`; plus
  the state the heartbeat reports. The commander lives in the simulator process
  (``sitl.commander.machine.Commander``, which satisfies this structurally and is what the
  in-process tests use); the bridge node uses ``mavlink_bridge.node.CommanderProxy``,
  which sends each request to it as a Zenoh query and reports its published status
  (a request it cannot get answered in time is refused as ``"busy"``). Goals (missions,
  DO_REPOSITION) go to the vehicle on the ``goal`` topic, not through this protocol.

Verdict reasons are short strings. The bridge maps them to MAV_RESULT:
``"no_setpoint_stream"``/``"busy"`` -> TEMPORARILY_REJECTED, ``"unsupported_mode"``/
``"unsupported"`` -> UNSUPPORTED, any other refusal -> DENIED.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class VelocityCommand:
    """A validated velocity setpoint in skyloop's frames.

    ``frame_is_body`` False: ``(vx, vy, vz)`` world ENU (east, north, up), m/s.
    ``frame_is_body`` True: body-horizontal FLU (forward, left, up), m/s, relative to the
    vehicle's *current* heading; the consumer rotates it by its current yaw (as PX4 does
    with MAV_FRAME_BODY_NED velocities), which the bridge cannot do without the state.
    ``yaw_rate``: rad/s, counter-clockwise positive (z up), in either frame.
    ``yaw``: an absolute heading target (ENU, CCW from east, rad) when the sender used a
    velocity + yaw type mask, else None; then ``yaw_rate`` is 0 and the consumer turns
    toward ``yaw``. Values are what arrived on the wire (float32, widened).
    """

    vx: float
    vy: float
    vz: float
    yaw_rate: float
    frame_is_body: bool
    yaw: float | None = None


@dataclass(frozen=True)
class VehicleTelemetry:
    """Vehicle state for MAVLink telemetry, in ENU/FLU, SI units.

    ``time``: seconds since the vehicle booted (the simulator's clock), gives
    ``time_boot_ms``. ``position``/``velocity``: world ENU, the local origin being the
    simulator's world origin. ``attitude``: ``(roll, pitch, yaw)`` ZYX Euler angles of the
    FLU body in ENU (pitch positive nose down, yaw CCW from east), see
    :mod:`mavlink_bridge.frames`. ``body_rates``: FLU rad/s.
    """

    time: float
    position: Vec3
    velocity: Vec3
    attitude: Vec3
    body_rates: Vec3 = (0.0, 0.0, 0.0)


class Verdict(Protocol):
    """The commander's answer to a request."""

    @property
    def accepted(self) -> bool: ...

    @property
    def reason(self) -> str: ...


class CommanderLike(Protocol):
    """The vehicle's commander as the MAVLink endpoint needs it (``now`` in seconds)."""

    @property
    def state(self) -> str:
        """``"DISARMED"``, ``"ARMED"``, ``"TAKEOFF"``, ``"OFFBOARD"``, ``"HOLD"``,
        ``"LAND"`` or ``"RTL"`` (a ``str`` enum is fine); the mode, reported with
        :attr:`armed` (``"TAKEOFF"`` disarmed: a takeoff waiting for arming)."""
        ...

    @property
    def armed(self) -> bool: ...

    @property
    def landed(self) -> bool: ...

    @property
    def failsafe(self) -> bool:
        """True while a failsafe action is in progress (heartbeat: MAV_STATE_CRITICAL)."""
        ...

    def arm(self, now: float) -> Verdict: ...

    def disarm(self, now: float, force: bool = False) -> Verdict: ...

    def takeoff(self, now: float, altitude: float | None = None) -> Verdict: ...

    def land(self, now: float) -> Verdict: ...

    def set_mode(self, now: float, state: str) -> Verdict: ...
