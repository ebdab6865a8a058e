"""A pymavlink ground station talking to a VehicleLink over real UDP on 127.0.0.1.

The vehicle side is a real ``sitl.commander.machine.Commander``, a kinematic point vehicle and a
:class:`~mavlink_bridge.vehicle_link.VehicleLink` on a simulated clock (``DT`` per tick).
Loopback UDP delivers a datagram before ``sendto`` returns, so "send, tick, drain" needs
no sleeps; every count is over simulated time.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

os.environ["MAVLINK20"] = "1"  # before mavutil is imported
from pymavlink import mavutil  # noqa: E402

from mavlink_bridge.interfaces import VehicleTelemetry  # noqa: E402
from mavlink_bridge.vehicle_link import LinkConfig, VehicleLink, VehicleLinkConfig  # noqa: E402
from sitl.commander.machine import Commander, VehicleSample  # noqa: E402

mavutil.set_dialect("common")
DT = 0.02


class GcsRig:
    """Ground station (system 255, component 190) + vehicle (system 1, component 1)."""

    def __init__(self, params_file: Path | str | None, **config: Any) -> None:
        self.gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255,
                                              source_component=190)
        port = self.gcs.port.getsockname()[1]
        self.commander = Commander()
        self.k = 0
        self.pos = [3.0, 4.0, 0.0]  # ENU
        self.vel = [0.0, 0.0, 0.0]
        self.yaw = 0.3
        config.setdefault("api", None)
        self.link = VehicleLink(self.commander, VehicleLinkConfig(
            gcs=LinkConfig(0, port), params_file=params_file, **config))
        self.tick()
        assert self.wait("HEARTBEAT") is not None  # the GCS now knows where to send

    @property
    def now(self) -> float:
        return self.k * DT

    def telemetry(self) -> VehicleTelemetry:
        return VehicleTelemetry(self.now, (self.pos[0], self.pos[1], self.pos[2]),
                                (self.vel[0], self.vel[1], self.vel[2]),
                                (0.05, -0.1, self.yaw), (0.01, 0.02, 0.03))

    def tick(self, n: int = 1) -> None:
        """Advance the vehicle ``n`` control steps: link, commander, point dynamics."""
        for _ in range(n):
            self.k += 1
            t = self.now
            self.link.poll(t)
            out = self.commander.step(t, VehicleSample(self.pos[2], self.vel[2], self.yaw,
                                                       self.pos[2]))
            self.vel[2] = out.vz if self.commander.armed else 0.0
            self.pos[2] = max(0.0, self.pos[2] + self.vel[2] * DT)
            if self.pos[2] == 0.0:  # on the ground
                self.vel[2] = max(0.0, self.vel[2])
            self.link.update_telemetry(self.telemetry())
            for e in self.commander.pop_events():
                self.link.statustext(e.text, e.severity)

    def drain(self) -> list[Any]:
        """Every message waiting at the ground station, in arrival order."""
        out = []
        while (m := self.gcs.recv_match(blocking=False)) is not None:
            out.append(m)
        return out

    def exchange(self, send: Any = None, ticks: int = 1) -> list[Any]:
        """Send a message (a pymavlink message object), tick, return what came back."""
        self.drain()
        if send is not None:
            self.gcs.mav.send(send)
        out = []
        for _ in range(ticks):  # drain every tick: the socket buffer holds only so much
            self.tick()
            out.extend(self.drain())
        return out

    def wait(self, kind: str, timeout: float = 2.0) -> Any:
        return self.gcs.recv_match(type=kind, blocking=True, timeout=timeout)

    def close(self) -> None:
        self.link.close()
        self.gcs.close()


def of_type(msgs: list[Any], kind: str) -> list[Any]:
    return [m for m in msgs if m.get_type() == kind]
