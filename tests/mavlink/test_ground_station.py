"""A pymavlink ground station flies ``skyloop up --policy none`` (real processes, loopback).

The vehicle waits on the ground, disarmed (HEARTBEAT: STANDBY, not armed); the ground
station reads the parameter list (PARAM_REQUEST_LIST: the table of ``bus/params.py``,
``--param`` values in it), reads one by name, sets one (echoed, persisted under
``$XDG_STATE_HOME``), takes off as QGroundControl's PX4 Takeoff does (NAV_TAKEOFF while
disarmed with param7 = GLOBAL_POSITION_INT.alt + 3 m: accepted, the heartbeat shows
AUTO.TAKEOFF disarmed; then ARM: LOCAL_POSITION_NED, altitude rises under JSBSim),
streams velocity setpoints and switches to OFFBOARD, then stops streaming: the sim's
commander holds, lands and disarms, each step announced by STATUSTEXT.
COM_OF_LOSS_T and SKY_HOLD_LAND_T are shortened with ``--param``.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from loopback import free_port, interrupt, sigint_default

os.environ["MAVLINK20"] = "1"  # before mavutil is imported
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from bus import params as table  # noqa: E402
from mavlink_bridge.modes import AUTO_TAKEOFF, encode_custom_mode  # noqa: E402
from skyloop import launcher  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
ARMED = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
OFFBOARD_MODE = encode_custom_mode(6, 0)


class GroundStation:
    """A pymavlink GCS on the vehicle's GCS port; records what it hears."""

    def __init__(self, port: int) -> None:
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255,
                                               source_component=190, dialect="common")
        self.heartbeat = None
        self.z_ned: list[float] = []
        self.amsl: list[float] = []  # GLOBAL_POSITION_INT.alt, m
        self.texts: list[str] = []
        self.acks: dict[int, int] = {}
        self.params: dict[str, tuple[float, int, int, int]] = {}  # value, type, index, count
        self.streaming = False
        self._next_sp = 0.0
        self._ms = 0

    def pump(self, seconds: float = 0.05) -> None:
        end = time.monotonic() + seconds
        while True:
            msg = self.conn.recv_match(blocking=True, timeout=0.01)
            if msg is not None and msg.get_srcSystem() == 1:
                kind = msg.get_type()
                if kind == "HEARTBEAT":
                    self.heartbeat = msg
                elif kind == "LOCAL_POSITION_NED":
                    self.z_ned.append(msg.z)
                elif kind == "GLOBAL_POSITION_INT":
                    self.amsl.append(msg.alt / 1000.0)
                elif kind == "STATUSTEXT":
                    self.texts.append(msg.text)
                elif kind == "COMMAND_ACK":
                    self.acks[msg.command] = msg.result
                elif kind == "PARAM_VALUE":
                    self.params[msg.param_id] = (msg.param_value, msg.param_type,
                                                 msg.param_index, msg.param_count)
            if self.streaming and time.monotonic() >= self._next_sp:
                self._next_sp = time.monotonic() + 0.1
                self._ms += 100
                self.conn.mav.set_position_target_local_ned_send(
                    self._ms, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 0x05C7, 0, 0, 0,
                    0.0, 0.0, 0.0, 0, 0, 0, 0, 0)
            if time.monotonic() >= end:
                return

    def until(self, cond, timeout: float, what: str) -> None:
        end = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > end:
                raise AssertionError(f"timed out waiting for {what}; heard {self.texts}")
            self.pump()

    def command(self, command: int, *params: float, timeout: float = 5.0) -> int:
        self.acks.pop(command, None)
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(1, 1, command, 0, *p)
        self.until(lambda: command in self.acks, timeout, f"COMMAND_ACK {command}")
        return self.acks[command]

    @property
    def armed(self) -> bool:
        return bool(self.heartbeat.base_mode & ARMED)


@pytest.fixture
def vehicle(tmp_path: Path):
    udp = [free_port(socket.SOCK_DGRAM) for _ in range(4)]
    gcs = GroundStation(udp[2])
    cmd = [sys.executable, "-m", "skyloop", "up", "--policy", "none", "--hub",
           f"tcp/127.0.0.1:{free_port()}", "--api-port", str(udp[0]), "--api-local-port",
           str(udp[1]), "--gcs-port", str(udp[2]), "--gcs-local-port", str(udp[3]),
           "--param", "COM_OF_LOSS_T=0.5", "--param", "SKY_HOLD_LAND_T=1.0"]
    env = dict(os.environ, XDG_STATE_HOME=str(tmp_path))
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=False,
                            preexec_fn=sigint_default)
    try:
        yield gcs, tmp_path / "skyloop" / "params-sys1.json"
    finally:
        out = interrupt(proc)
        assert "policy" not in [n[0] for n in map(launcher.started, out.splitlines()) if n]
        gcs.conn.close()


def test_ground_station_flies_the_vehicle(vehicle) -> None:
    gcs, params_file = vehicle
    gcs.until(lambda: gcs.heartbeat is not None, 120.0, "the vehicle's heartbeat")
    assert not gcs.armed and gcs.heartbeat.system_status == mavlink.MAV_STATE_STANDBY
    assert gcs.heartbeat.autopilot == mavlink.MAV_AUTOPILOT_PX4
    # Parameters: the whole table, in order, with the --param values.
    names = [p.name for p in table.PARAMS]
    gcs.conn.mav.param_request_list_send(1, 1)
    gcs.until(lambda: set(gcs.params) == set(names), 5.0, "every PARAM_VALUE")
    assert {n: gcs.params[n][2:] for n in names} == \
        {n: (i, len(names)) for i, n in enumerate(names)}
    expected = dict(table.defaults(), COM_OF_LOSS_T=0.5, SKY_HOLD_LAND_T=1.0)
    assert {n: round(gcs.params[n][0], 5) for n in names} == expected
    assert all(gcs.params[n][1] == mavlink.MAV_PARAM_TYPE_REAL32 for n in names)
    gcs.params.clear()
    gcs.conn.mav.param_request_read_send(1, 1, b"MPC_Z_VEL_MAX", -1)
    gcs.until(lambda: "MPC_Z_VEL_MAX" in gcs.params, 5.0, "PARAM_VALUE MPC_Z_VEL_MAX")
    assert gcs.params["MPC_Z_VEL_MAX"][0] == table.BY_NAME["MPC_Z_VEL_MAX"].default
    gcs.conn.mav.param_set_send(1, 1, b"SKY_FLIGHT_LVL", 5.0, mavlink.MAV_PARAM_TYPE_REAL32)
    gcs.until(lambda: "SKY_FLIGHT_LVL" in gcs.params, 5.0, "PARAM_VALUE SKY_FLIGHT_LVL")
    assert gcs.params["SKY_FLIGHT_LVL"][0] == 5.0
    saved = json.loads(params_file.read_text())["params"]
    assert saved == {"SKY_FLIGHT_LVL": 5.0}  # only what a ground station set; --param: not kept
    gcs.until(lambda: len(gcs.z_ned) > 5 and gcs.amsl, 10.0, "LOCAL_POSITION_NED")
    ground = gcs.z_ned[-1]
    # QGroundControl's PX4 Takeoff: NAV_TAKEOFF disarmed (AMSL altitude), ARM once accepted.
    nan = float("nan")
    assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, -1, 0, 0, nan, nan, nan,
                       gcs.amsl[-1] + 3.0) == mavlink.MAV_RESULT_ACCEPTED
    gcs.until(lambda: gcs.heartbeat.custom_mode == AUTO_TAKEOFF.custom_mode, 5.0,
              "AUTO.TAKEOFF heartbeat")
    assert not gcs.armed and "Takeoff pending: 3.0 m, arm to start" in gcs.texts
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0) == mavlink.MAV_RESULT_ACCEPTED
    gcs.until(lambda: gcs.armed, 5.0, "armed heartbeat")
    gcs.until(lambda: gcs.z_ned[-1] < ground - 2.0, 20.0, "altitude up 2 m")  # NED: up < 0
    gcs.streaming = True
    gcs.pump()  # the first setpoint goes out at once; PX4's rule: one recent setpoint
    assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0) == mavlink.MAV_RESULT_ACCEPTED
    gcs.until(lambda: gcs.heartbeat.custom_mode == OFFBOARD_MODE, 5.0, "OFFBOARD")
    gcs.pump(1.0)
    assert gcs.heartbeat.custom_mode == OFFBOARD_MODE  # the stream keeps it
    gcs.streaming = False
    gcs.until(lambda: "Landed, disarmed" in gcs.texts, 30.0, "landed and disarmed")
    gcs.until(lambda: not gcs.armed, 5.0, "disarmed heartbeat")
    for text in ("Armed", "Takeoff to 3.0 m", "Offboard", "Failsafe: setpoints lost, holding",
                 "Failsafe: landing", "Landed, disarmed"):
        assert text in gcs.texts
    assert gcs.texts.index("Failsafe: setpoints lost, holding") < \
        gcs.texts.index("Failsafe: landing") < gcs.texts.index("Landed, disarmed")
    assert abs(gcs.z_ned[-1] - ground) < 0.3  # back on the ground
