"""MAVSDK (from PyPI, its bundled C++ library) flies ``skyloop up --policy none``.

MAVSDK connects as PX4 SITL users do, on the API link (the vehicle sends to the port
skyloop's policy would listen on; with ``--policy none`` it is free): it discovers a PX4
autopilot, reads every parameter, sets the takeoff altitude (``set_takeoff_altitude``:
the MIS_TAKEOFF_ALT parameter), arms, takes off to it (``takeoff()`` sends NaN: the
vehicle flies MIS_TAKEOFF_ALT), sets a body-frame velocity and starts OFFBOARD at once
(PX4's rule: one recent setpoint), flies it and lands, the vehicle disarming on
touchdown.
"""

from __future__ import annotations

import asyncio
import math
import os
import socket
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest
from loopback import free_port, interrupt, sigint_default

pytest.importorskip("mavsdk.asyncio", reason="mavsdk not installed (pip install -e '.[test]')")
from mavsdk.asyncio import Autopilot, ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.asyncio.plugins.action.action import ActionAsync  # noqa: E402
from mavsdk.asyncio.plugins.offboard.offboard import OffboardAsync  # noqa: E402
from mavsdk.asyncio.plugins.param.param import ParamAsync  # noqa: E402
from mavsdk.asyncio.plugins.telemetry.telemetry import TelemetryAsync  # noqa: E402
from mavsdk.plugins.offboard import VelocityBodyYawspeed  # noqa: E402
from mavsdk.plugins.telemetry import FlightMode, LandedState  # noqa: E402

from bus import params as table  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
TAKEOFF_ALT = 3.5  # m, set through MIS_TAKEOFF_ALT (default 2.5)


@pytest.fixture
def api_port(tmp_path: Path):
    udp = [free_port(socket.SOCK_DGRAM) for _ in range(4)]
    cmd = [sys.executable, "-m", "skyloop", "up", "--policy", "none", "--hub",
           f"tcp/127.0.0.1:{free_port()}", "--api-port", str(udp[0]), "--api-local-port",
           str(udp[1]), "--gcs-port", str(udp[2]), "--gcs-local-port", str(udp[3]),
           "--param", "COM_OF_LOSS_T=0.5"]
    env = dict(os.environ, XDG_STATE_HOME=str(tmp_path))
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, preexec_fn=sigint_default)
    try:
        yield udp[0]
    finally:
        interrupt(proc)


async def until(cond: Callable[[], Awaitable[bool]], timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not await cond():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.1)


async def fly(port: int) -> None:
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as mavsdk:
        await mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = await mavsdk.first_autopilot(timeout_s=120.0)
        assert system is not None, "no autopilot discovered"
        assert await system.autopilot_type() == Autopilot.PX4
        assert await system.get_system_id() == 1
        tel, act = TelemetryAsync(system), ActionAsync(system)
        off, par = OffboardAsync(system), ParamAsync(system)

        every = {p.name: p.value for p in (await par.get_all_params()).float_params}
        assert set(every) == {p.name for p in table.PARAMS}
        assert every["COM_OF_LOSS_T"] == 0.5 and every["SKY_FLIGHT_LVL"] == 3.5
        assert not await tel.armed() and await tel.flight_mode() == FlightMode.HOLD

        await act.set_takeoff_altitude(TAKEOFF_ALT)  # MIS_TAKEOFF_ALT, not the default
        assert await act.get_takeoff_altitude() == TAKEOFF_ALT
        await act.arm()
        await act.takeoff()
        await until(lambda: _above(tel, 2.0), 30.0, "2 m above home")
        await until(lambda: _mode(tel, FlightMode.HOLD), 20.0, "takeoff done (Hold)")
        # MIS_TAKEOFF_ALT flown (the default, 2.5 m, would never get there); telemetry
        # lags the mode change, so wait for it to settle
        await until(lambda: _near(tel, TAKEOFF_ALT, 0.25), 10.0, f"{TAKEOFF_ALT} m above home")

        await off.set_velocity_body(VelocityBodyYawspeed(1.0, 0.0, 0.0, 0.0))
        await off.start()  # right after the first setpoint, as PX4 allows
        # start() returns on the COMMAND_ACK; the heartbeat that shows the mode follows it
        await until(lambda: _mode(tel, FlightMode.OFFBOARD), 3.0, "OFFBOARD in the heartbeat")
        start = (await tel.position_velocity_ned()).position
        await until(lambda: _moved(tel, start, 1.5), 15.0, "1.5 m flown in OFFBOARD")
        assert await tel.flight_mode() == FlightMode.OFFBOARD  # MAVSDK's stream keeps it

        await act.land()
        await until(lambda: _not_armed(tel), 40.0, "landed and disarmed")
        await until(lambda: _landed(tel), 5.0, "landed state ON_GROUND")


async def _above(tel: TelemetryAsync, metres: float) -> bool:
    return (await tel.position()).relative_altitude_m > metres


async def _near(tel: TelemetryAsync, metres: float, tolerance: float) -> bool:
    return abs((await tel.position()).relative_altitude_m - metres) < tolerance


async def _mode(tel: TelemetryAsync, mode: FlightMode) -> bool:
    return await tel.flight_mode() == mode


async def _moved(tel: TelemetryAsync, start: object, metres: float) -> bool:
    p = (await tel.position_velocity_ned()).position
    return math.hypot(p.north_m - start.north_m, p.east_m - start.east_m) > metres


async def _not_armed(tel: TelemetryAsync) -> bool:
    return not await tel.armed()


async def _landed(tel: TelemetryAsync) -> bool:
    return await tel.landed_state() == LandedState.ON_GROUND


def test_mavsdk_flies_the_vehicle(api_port: int) -> None:
    asyncio.run(fly(api_port))
