"""A pymavlink ground station flies ``skyloop up --policy none`` (real processes, loopback).

The vehicle waits on the ground, disarmed (HEARTBEAT: STANDBY, not armed); the ground
station arms (ACK accepted), takes off (LOCAL_POSITION_NED: altitude rises under
JSBSim), streams velocity setpoints and switches to OFFBOARD, then stops streaming: the
sim's commander holds, lands and disarms, each step announced by STATUSTEXT.
COM_OF_LOSS_T and SKY_HOLD_LAND_T are shortened with ``--param``.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from loopback import free_port

os.environ["MAVLINK20"] = "1"  # before mavutil is imported
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from mavlink_bridge.modes import encode_custom_mode  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
ARMED = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
OFFBOARD_MODE = encode_custom_mode(6, 0)


class GroundStation:
    """A pymavlink GCS on the vehicle's GCS port; records what it hears."""

    def __init__(self, port: int) -> None:
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255,
                                               source_component=190, dialect="common")
        self.heartbeat = None
        self.z_ned: list[float] = []
        self.texts: list[str] = []
        self.acks: dict[int, int] = {}
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
                elif kind == "STATUSTEXT":
                    self.texts.append(msg.text)
                elif kind == "COMMAND_ACK":
                    self.acks[msg.command] = msg.result
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
def vehicle():
    udp = [free_port(socket.SOCK_DGRAM) for _ in range(4)]
    gcs = GroundStation(udp[2])
    cmd = [sys.executable, "-m", "skyloop", "up", "--policy", "none", "--hub",
           f"tcp/127.0.0.1:{free_port()}", "--api-port", str(udp[0]), "--api-local-port",
           str(udp[1]), "--gcs-port", str(udp[2]), "--gcs-local-port", str(udp[3]),
           "--param", "COM_OF_LOSS_T=0.5", "--param", "SKY_HOLD_LAND_T=1.0"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=False)
    try:
        yield gcs
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            out = proc.communicate(timeout=15)[0]
        except subprocess.TimeoutExpired:
            proc.kill()
            out = proc.communicate()[0]
        assert "policy" not in [line.split()[1] for line in out.splitlines()
                                if line.startswith("started ")]
        gcs.conn.close()


def test_ground_station_flies_the_vehicle(vehicle) -> None:
    gcs = vehicle
    gcs.until(lambda: gcs.heartbeat is not None, 120.0, "the vehicle's heartbeat")
    assert not gcs.armed and gcs.heartbeat.system_status == mavlink.MAV_STATE_STANDBY
    gcs.until(lambda: len(gcs.z_ned) > 5, 10.0, "LOCAL_POSITION_NED")
    ground = gcs.z_ned[-1]
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0) == mavlink.MAV_RESULT_ACCEPTED
    gcs.until(lambda: gcs.armed, 5.0, "armed heartbeat")
    assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, float("nan"), 0, 0,
                       float("nan")) == mavlink.MAV_RESULT_ACCEPTED
    gcs.until(lambda: gcs.z_ned[-1] < ground - 2.0, 20.0, "altitude up 2 m")  # NED: up < 0
    gcs.streaming = True
    gcs.pump(1.0)  # > 2 Hz for a second
    assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0) == mavlink.MAV_RESULT_ACCEPTED
    gcs.until(lambda: gcs.heartbeat.custom_mode == OFFBOARD_MODE, 5.0, "OFFBOARD")
    gcs.pump(1.0)
    assert gcs.heartbeat.custom_mode == OFFBOARD_MODE  # the stream keeps it
    gcs.streaming = False
    gcs.until(lambda: "Landed, disarmed" in gcs.texts, 30.0, "landed and disarmed")
    gcs.until(lambda: not gcs.armed, 5.0, "disarmed heartbeat")
    for text in ("Armed", "Offboard", "Failsafe: setpoints lost, holding",
                 "Failsafe: landing", "Landed, disarmed"):
        assert text in gcs.texts
    assert gcs.texts.index("Failsafe: setpoints lost, holding") < \
        gcs.texts.index("Failsafe: landing") < gcs.texts.index("Landed, disarmed")
    assert abs(gcs.z_ned[-1] - ground) < 0.3  # back on the ground
