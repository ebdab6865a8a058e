"""MAVProxy (from PyPI, headless) flies ``skyloop up --policy none`` (real processes).

MAVProxy is the ground station on the vehicle's GCS port, with its default modules,
driven through its stdin exactly as a person types at its ``MAV>`` prompt (the commands
are in :data:`FLIGHT`). It forwards what it hears (``--out``) to a passive pymavlink
listener here, which checks the vehicle's side: heartbeats (PX4 autopilot, custom mode,
armed bit), LOCAL_POSITION_NED, STATUSTEXT and PARAM_VALUE. MAVProxy's own output gives
the COMMAND_ACKs and what it read of the parameters.

The flight: MAVProxy sees the vehicle and fetches the parameter list (MAVLink FTP is
refused at once, so it falls back to PARAM_REQUEST_LIST; COM_OF_LOSS_T shows the
``--param`` value), sets MPC_XY_VEL_MAX to 0.8 m/s, arms, takes off, streams
``velocity 2 0 0`` and switches to OFFBOARD (the vehicle flies, capped at 0.8 m/s: the
parameter took effect), then switches to AUTO.LAND: the vehicle lands and disarms.

MAVProxy 1.8.75's ``mode OFFBOARD`` / ``mode LAND`` fail for every PX4 vehicle ("required
argument is not a float": its mode module hands pymavlink's PX4 mode tuple to
``set_mode``), so the modes are set with ``long DO_SET_MODE 1 <main> <sub>``.
"""

from __future__ import annotations

import math
import os
import queue
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from loopback import free_port, interrupt, sigint_default, vehicle_messages

pytest.importorskip("MAVProxy", reason="MAVProxy not installed (pip install -e '.[test]')")
os.environ["MAVLINK20"] = "1"  # before mavutil is imported
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from bus import params as table  # noqa: E402
from mavlink_bridge.modes import AUTO_LAND, OFFBOARD  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SET_OFFBOARD = "long DO_SET_MODE 1 6 0"  # CUSTOM_MODE_ENABLED, PX4 main mode OFFBOARD
SET_LAND = "long DO_SET_MODE 1 4 6"  # AUTO (4), sub mode LAND (6)
FLIGHT = ["param show COM_OF_LOSS_T", "param set MPC_XY_VEL_MAX 0.8", "arm throttle",
          "takeoff 3", "repeat add 0.1 velocity 2 0 0", SET_OFFBOARD, SET_LAND,
          "repeat remove 0"]


class MavProxy:
    """``python -m MAVProxy.mavproxy`` with a pipe for its stdin and its lines kept."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        env = dict(os.environ, HOME=str(cwd), MAVLINK20="1")  # its ~/.mavproxy, tile cache
        self.proc = subprocess.Popen([sys.executable, "-m", "MAVProxy.mavproxy", *args],
                                     cwd=cwd, env=env, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, bufsize=1)
        self.lines: list[str] = []
        self._q: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self._q.put(line.rstrip("\n"))

    def take(self) -> list[str]:
        while True:
            try:
                self.lines.append(self._q.get_nowait())
            except queue.Empty:
                return self.lines

    def send(self, command: str) -> None:
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def said(self, text: str, since: int = 0) -> bool:
        return any(text in line for line in self.take()[since:])

    def close(self) -> str:
        try:
            self.proc.stdin.close()  # EOF on its prompt: it exits
            self.proc.wait(10)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()
        return "\n".join(self.take())


class Listener:
    """A passive pymavlink endpoint for MAVProxy's ``--out``: the vehicle's messages."""

    def __init__(self, port: int) -> None:
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="common")
        self.heartbeat = None
        self.autopilots: set[int] = set()
        self.pos: list[tuple[float, float, float, float, float, float]] = []
        self.texts: list[str] = []
        self.params: dict[str, float] = {}
        self.landed_state = -1

    def pump(self, seconds: float = 0.05) -> None:
        for msg in vehicle_messages(self.conn, seconds):
            kind = msg.get_type()
            if kind == "HEARTBEAT":
                self.heartbeat = msg
                self.autopilots.add(msg.autopilot)
            elif kind == "LOCAL_POSITION_NED":
                self.pos.append((msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz))
            elif kind == "STATUSTEXT":
                self.texts.append(msg.text)
            elif kind == "PARAM_VALUE":
                self.params[msg.param_id] = msg.param_value
            elif kind == "EXTENDED_SYS_STATE":
                self.landed_state = msg.landed_state

    @property
    def armed(self) -> bool:
        return bool(self.heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    @property
    def custom_mode(self) -> int:
        return self.heartbeat.custom_mode


@pytest.fixture
def rig(tmp_path: Path):
    udp = [free_port(socket.SOCK_DGRAM) for _ in range(5)]
    cmd = [sys.executable, "-m", "skyloop", "up", "--policy", "none", "--hub",
           f"tcp/127.0.0.1:{free_port()}", "--api-port", str(udp[0]), "--api-local-port",
           str(udp[1]), "--gcs-port", str(udp[2]), "--gcs-local-port", str(udp[3]),
           "--param", "COM_OF_LOSS_T=0.5"]
    env = dict(os.environ, XDG_STATE_HOME=str(tmp_path / "state"))
    vehicle = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True, preexec_fn=sigint_default)
    listener = Listener(udp[4])
    mavproxy = MavProxy([f"--master=udpin:127.0.0.1:{udp[2]}", f"--out=udp:127.0.0.1:{udp[4]}",
                         "--no-state", f"--state-basedir={tmp_path}"], tmp_path)
    try:
        yield mavproxy, listener
    finally:
        log = mavproxy.close()
        interrupt(vehicle)
        listener.conn.close()
        print(log)  # shown when the test fails


def test_mavproxy_flies_the_vehicle(rig) -> None:
    mp, ear = rig

    def until(cond: Callable[[], bool], timeout: float, what: str,
              every: float = 0.0, resend: str = "") -> None:
        """Pump the listener until ``cond``; optionally re-send a command every ``every`` s."""
        end = time.monotonic() + timeout
        next_send = time.monotonic() + every
        while not cond():
            if time.monotonic() > end:
                raise AssertionError(f"timed out waiting for {what}; vehicle said {ear.texts}")
            if resend and time.monotonic() >= next_send:
                mp.send(resend)
                next_send = time.monotonic() + every
            ear.pump()

    # It sees the vehicle: a PX4 quadrotor, system 1, on the ground, disarmed.
    until(lambda: mp.said("Detected vehicle 1:1") and ear.heartbeat is not None, 120.0,
          "MAVProxy to detect the vehicle")
    assert ear.autopilots == {mavlink.MAV_AUTOPILOT_PX4}
    assert ear.heartbeat.type == mavlink.MAV_TYPE_QUADROTOR and not ear.armed
    until(lambda: len(ear.pos) > 5, 10.0, "LOCAL_POSITION_NED")
    ground = ear.pos[-1][2]

    # It reads the parameters: the whole list, COM_OF_LOSS_T as --param set it.
    until(lambda: mp.said(f"Received {len(table.PARAMS)} parameters"), 30.0,
          "the parameter list")
    # MAVProxy forwards them to the listener after it has counted them: wait for them there
    wanted = {"COM_OF_LOSS_T", "SKY_HOLD_LAND_T", "MPC_XY_VEL_MAX", "SKY_FLIGHT_LVL"}
    until(lambda: wanted <= set(ear.params), 10.0, f"PARAM_VALUE of {sorted(wanted)}")
    mark = len(mp.take())
    mp.send(FLIGHT[0])  # param show COM_OF_LOSS_T
    until(lambda: any(line.split()[-2:] == ["COM_OF_LOSS_T", "0.5"] for line in mp.take()[mark:]),
          5.0, "param show COM_OF_LOSS_T = 0.5")

    # A param set takes: the vehicle echoes the new value (PARAM_VALUE).
    mp.send(FLIGHT[1])  # param set MPC_XY_VEL_MAX 0.8
    until(lambda: abs(ear.params.get("MPC_XY_VEL_MAX", 0.0) - 0.8) < 1e-6, 5.0,
          "PARAM_VALUE MPC_XY_VEL_MAX 0.8")

    # Arm, take off.
    mark = len(mp.take())
    mp.send(FLIGHT[2])  # arm throttle
    until(lambda: ear.armed, 10.0, "armed heartbeat")
    assert mp.said("Got COMMAND_ACK: COMPONENT_ARM_DISARM: ACCEPTED", mark)
    mp.send(FLIGHT[3])  # takeoff 3
    until(lambda: ear.pos[-1][2] < ground - 2.0, 30.0, "altitude up 2 m")  # NED: up < 0
    until(lambda: "Takeoff complete, holding" in ear.texts, 20.0, "takeoff complete")
    assert mp.said("Got COMMAND_ACK: NAV_TAKEOFF: ACCEPTED", mark)

    # Offboard: stream velocity setpoints, then switch (PX4's rule: a recent setpoint;
    # re-sent in case MAVProxy's first repeat had not gone out yet).
    mp.send(FLIGHT[4])  # repeat add 0.1 velocity 2 0 0
    ear.pump(0.3)
    mark = len(mp.take())
    until(lambda: ear.custom_mode == OFFBOARD.custom_mode, 15.0, "OFFBOARD in the heartbeat",
          every=2.0, resend=FLIGHT[5])
    assert mp.said("Got COMMAND_ACK: DO_SET_MODE: ACCEPTED", mark) and "Offboard" in ear.texts
    start = len(ear.pos)
    x0, y0 = ear.pos[-1][:2]
    until(lambda: math.dist(ear.pos[-1][:2], (x0, y0)) > 2.0, 20.0, "2 m flown in OFFBOARD")
    assert ear.custom_mode == OFFBOARD.custom_mode  # MAVProxy's stream keeps it
    # 2 m/s asked; the sim's autopilot caps each horizontal axis at MPC_XY_VEL_MAX = 0.8
    # (flown: up to ~0.88). Uncapped, one axis of a 2 m/s velocity is >= 2/sqrt(2) = 1.41.
    axes = [max(abs(p[3]), abs(p[4])) for p in ear.pos[start:]]
    assert 0.5 < max(axes) < 1.2

    # Land: the mode change is acknowledged, the vehicle descends, touches down, disarms.
    mark = len(mp.take())
    mp.send(FLIGHT[6])  # long DO_SET_MODE 1 4 6
    until(lambda: ear.custom_mode == AUTO_LAND.custom_mode or "Landing" in ear.texts, 10.0,
          "AUTO.LAND")
    assert mp.said("Got COMMAND_ACK: DO_SET_MODE: ACCEPTED", mark)
    until(lambda: "Landed, disarmed" in ear.texts, 40.0, "landed and disarmed")
    until(lambda: not ear.armed, 5.0, "disarmed heartbeat")
    mp.send(FLIGHT[7])  # repeat remove 0
    assert abs(ear.pos[-1][2] - ear.pos[start][2]) > 2.0  # came down from flight level
    assert abs(ear.pos[-1][5]) < 0.3  # at rest
    until(lambda: ear.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND, 5.0, "on ground")
