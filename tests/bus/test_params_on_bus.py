"""Ground-station parameters reach the nodes that apply them (issue 5 §1).

Real parts on loopback: the bridge node (own thread) with a pymavlink ground station on
its GCS link, the sim's :class:`~sitl.node.vehicle_service.VehicleService` (what applies the
sim's parameters) and a :class:`~perception.node.PerceptionNode` (``SKY_ICO_RADIUS``),
each on its own Zenoh session. Checked: when the vehicle appears the bridge sends its
chosen values (the file's and ``--param`` overrides, which are not persisted); a PARAM_SET from the
ground station is echoed, persisted and applied by the sim (SKY_ICO_RADIUS: its LiDAR's
range) and by perception; bad
values on the bus are counted by perception, never applied.
"""

from __future__ import annotations

import json
import math
import os
import socket
import threading
import time

from loopback import free_port, wait_for

os.environ["MAVLINK20"] = "1"  # before mavutil is imported
from pymavlink import mavutil  # noqa: E402

from bus import keys  # noqa: E402
from bus import messages as m  # noqa: E402
from bus.node import Bus  # noqa: E402
from bus.session import SessionConfig  # noqa: E402
from mavlink_bridge.node import BridgeNode  # noqa: E402
from mavlink_bridge.transport import mavlink  # noqa: E402
from mavlink_bridge.vehicle_link import LinkConfig, VehicleLinkConfig  # noqa: E402
from perception.node import PerceptionNode  # noqa: E402
from sitl.commander.machine import Commander  # noqa: E402
from sitl.node.vehicle_service import VehicleService  # noqa: E402


def _param_set(gcs, name: str, value: float) -> None:
    gcs.mav.param_set_send(1, 1, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32)


def test_parameters_flow_from_ground_station_to_sim_and_perception(tmp_path):
    cfg = SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")
    buses = [Bus.open(cfg) for _ in range(4)]
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255,
                                     source_component=190, dialect="common")
    gcs_port = gcs.port.getsockname()[1]
    pfile = tmp_path / "params.json"
    pfile.write_text(json.dumps({"format": "skyloop-params/1",
                                 "params": {"MPC_Z_VEL_MAX": 1.5}}))
    bridge = BridgeNode(buses[0], "uav1", VehicleLinkConfig(
        api=None, gcs=LinkConfig(free_port(socket.SOCK_DGRAM), gcs_port),
        params_file=str(pfile)), param_overrides={"COM_OF_LOSS_T": 0.5})
    stop = threading.Event()
    thread = threading.Thread(target=bridge.run, args=(stop.is_set,), daemon=True)
    perception = PerceptionNode(buses[2], "uav1")
    seen: list[tuple[str, float]] = []
    buses[3].subscribe(keys.PARAMS, "uav1", lambda msg: seen.append((msg.name, msg.value)))
    commander = Commander()
    from sitl.episode import EpisodeSim

    sim = EpisodeSim()  # the sim's LiDAR follows SKY_ICO_RADIUS
    service = VehicleService(buses[1], "uav1", commander, None, sensor=sim)
    thread.start()
    try:
        t = [0.0]

        def vehicle_step() -> None:  # what the sim does each control step
            service.serve(t[0])
            service.publish_status(0.0, t[0], force=True)
            t[0] += 0.1

        # The vehicle appears: the bridge sends what was chosen (the file's values and
        # the override), not untouched defaults (a node's own --param stands for those).
        wait_for(lambda: (vehicle_step(), len(seen) >= 2)[1], 10.0,
                 "the chosen parameters on the bus", poll=0.05)
        assert dict(seen) == {"COM_OF_LOSS_T": 0.5, "MPC_Z_VEL_MAX": 1.5}
        wait_for(lambda: (vehicle_step(), commander.config.setpoint_timeout == 0.5)[1], 5.0,
                 "the sim applied the override", poll=0.05)
        assert json.loads(pfile.read_text())["params"] == {"MPC_Z_VEL_MAX": 1.5}

        # A ground station sets two parameters: echoed, persisted, applied.
        wait_for(lambda: gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=0.1)
                 is not None or (vehicle_step() and False), 10.0, "a heartbeat")
        _param_set(gcs, "GF_MAX_HOR_DIST", 120.0)
        _param_set(gcs, "SKY_ICO_RADIUS", 6.0)
        echoed: dict[str, float] = {}

        def echoes() -> bool:
            vehicle_step()
            while (msg := gcs.recv_match(type="PARAM_VALUE", blocking=False)) is not None:
                echoed[msg.param_id] = msg.param_value
            return {"GF_MAX_HOR_DIST", "SKY_ICO_RADIUS"} <= set(echoed)

        wait_for(echoes, 10.0, "PARAM_VALUE echoes", poll=0.05)
        assert echoed == {"GF_MAX_HOR_DIST": 120.0, "SKY_ICO_RADIUS": 6.0}
        wait_for(lambda: (vehicle_step(), commander.config.geofence == 120.0)[1], 5.0,
                 "the sim applied GF_MAX_HOR_DIST", poll=0.05)
        wait_for(lambda: perception.config.radius == 6.0, 5.0, "perception's new radius")
        assert perception.ico.radius == 6.0
        assert sim.lidar.config.max_range == 6.5  # the LiDAR reaches the new radius
        saved = json.loads(pfile.read_text())["params"]
        # The file holds what a ground station set, earlier runs included; no override.
        assert saved == {"GF_MAX_HOR_DIST": 120.0, "SKY_ICO_RADIUS": 6.0, "MPC_Z_VEL_MAX": 1.5}

        # Bad values on the bus: counted by perception, nothing applied, no crash.
        pub = buses[3].publisher(keys.PARAMS, "uav1")
        pub.put(m.parameter("SKY_ICO_RADIUS", math.nan))
        pub.put(m.parameter("SKY_ICO_RADIUS", 1e6))
        pub.put(m.parameter("NO_SUCH_PARAM", 1.0))
        wait_for(lambda: perception.param_rejects == 3, 5.0, "perception's rejections")
        assert perception.config.radius == 6.0
        assert bridge.link.params.counters["load_error"] == 0
    finally:
        stop.set()
        thread.join(5.0)
        bridge.close()
        perception.close()
        gcs.close()
        for b in buses:
            b.close()
        time.sleep(0)
