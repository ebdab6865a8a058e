"""A bus that lets no one in (issue 13 §4), on loopback with real Zenoh sessions: a router
on a ``tls/`` endpoint with the configuration ``skyloop certs`` writes (mutual TLS,
access control by certificate common name), nodes as clients with theirs."""

from __future__ import annotations

import re
import shutil
import socket
import threading
import time

import pytest
from loopback import free_port, wait_for

from bus import keys
from bus import messages as m
from bus.certs import make_certs
from bus.node import Bus
from bus.session import SessionConfig, SessionError, run_router

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="no openssl command")


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    return make_certs(tmp_path_factory.mktemp("certs"), ("router", "sim", "perception",
                                                         "bridge"))


@pytest.fixture
def router(certs):
    endpoint = f"tls/localhost:{free_port()}"
    stop = threading.Event()
    thread = threading.Thread(target=run_router, args=(endpoint, stop, SessionConfig(
        mode="router", config_file=str(certs / "router.json5"))), daemon=True)
    thread.start()
    time.sleep(1.0)  # listening
    yield endpoint
    stop.set()
    thread.join(5.0)


def client(endpoint: str, config_file: str | None) -> Bus:
    return Bus.open(SessionConfig(mode="client", connect=(endpoint,), config_file=config_file,
                                  connect_timeout_s=3.0))


def setpoint(tag: float):
    """A setpoint told apart by its x velocity."""
    return m.velocity_setpoint((tag, 0, 0), 0.0, 0.1, body=True)


def test_only_the_bridge_commands_the_vehicle(certs, router):
    sim, perception, bridge = (client(router, str(certs / f"{n}.json5"))
                               for n in ("sim", "perception", "bridge"))
    got: list[object] = []
    try:
        sim.subscribe(keys.CMD_VEL, "uav1", lambda msg: got.append(msg.velocity.x))
        sim.subscribe(keys.OBSERVATION, "uav1", lambda msg: got.append("observation"))
        time.sleep(1.0)  # declarations reach the router
        perception.publisher(keys.CMD_VEL, "uav1").put(setpoint(1.0))
        # a put on a wildcard key reaches every matching subscriber (cmd_vel's among
        # them) unless the router refuses it: no rule allows one
        for wildcard in ("skyloop/**", "skyloop/*/cmd_vel"):
            perception.session.put(wildcard, m.encode(setpoint(3.0)))
        bridge.publisher(keys.CMD_VEL, "uav1").put(setpoint(2.0))
        perception.publisher(keys.OBSERVATION, "uav1").put(m.observation([0.0] * 35, 0.1))
        wait_for(lambda: len(got) >= 2, 5.0, "the bridge's setpoint and the observation")
        time.sleep(0.5)
        # perception's setpoints were dropped at the router; its observation went through
        assert sorted(map(str, got)) == ["2.0", "observation"], got
    finally:
        for b in (sim, perception, bridge):
            b.close()


def test_a_later_certificate_of_the_ca_reads_but_cannot_command(certs, router):
    """A certificate the same CA signs after the router's configuration was written
    (``skyloop certs --nodes gcs``): its name is in no rule, so it is a read-only tool.
    It receives telemetry; its setpoints, goals, parameters, commander requests, wildcard
    puts, telemetry and readiness token reach no one, while the bridge's, sent after
    them on the same router, do."""
    make_certs(certs, ("gcs",))  # the same CA (certs/ca.pem), router.json5 untouched
    assert "gcs" not in (certs / "router.json5").read_text()
    sim, gcs, bridge = (client(router, str(certs / f"{n}.json5"))
                        for n in ("sim", "gcs", "bridge"))
    got: list[tuple[str, object]] = []
    odom: list[float] = []
    ready: list[str] = []
    try:
        sim.subscribe(keys.CMD_VEL, "uav1", lambda msg: got.append(("cmd_vel", msg.velocity.x)))
        sim.subscribe(keys.GOAL, "uav1", lambda msg: got.append(("goal", msg.header.frame_id)))
        sim.subscribe(keys.PARAMS, "uav1", lambda msg: got.append(("params", msg.name)))
        sim.subscribe(keys.OBSERVATION, "uav1", lambda msg: got.append(("observation", 0)))
        sim.watch_ready("uav1", lambda node, alive: alive and ready.append(node))
        requests = sim.queryable(keys.COMMAND, "uav1")
        gcs.subscribe(keys.ODOM, "uav1", lambda msg: odom.append(msg.header.stamp.sec))
        time.sleep(1.0)  # declarations reach the router

        # what a ground tool may do: read the vehicle's telemetry
        sim.publisher(keys.ODOM, "uav1").put(m.odometry((0, 0, 0), (0, 0, 0), (0, 0, 0, 1), 7.0))
        wait_for(lambda: odom == [7], 5.0, "the sim's odometry at the unlisted tool")

        # what it may not: anything the vehicle (or the stack) would act on
        gcs.publisher(keys.CMD_VEL, "uav1").put(setpoint(1.0))
        gcs.publisher(keys.GOAL, "uav1").put(m.pose_stamped((1, 2, 3), 0.1, frame_id="gcs"))
        gcs.publisher(keys.PARAMS, "uav1").put(m.parameter("gcs", 1.0))
        gcs.session.put("skyloop/*/cmd_vel", m.encode(setpoint(3.0)))
        gcs.publisher(keys.OBSERVATION, "uav1").put(m.observation([0.0] * 35, 0.1))
        gcs.declare_ready("uav1", "gcs")
        assert gcs.query(keys.COMMAND, "uav1", m.vehicle_command("gcs"), m.COMMAND_ACK,
                         timeout=0.5) is None

        # the bridge, on the same router, after it: all of its get through
        bridge.publisher(keys.CMD_VEL, "uav1").put(setpoint(2.0))
        bridge.publisher(keys.GOAL, "uav1").put(m.pose_stamped((1, 2, 3), 0.1,
                                                              frame_id="bridge"))
        bridge.publisher(keys.PARAMS, "uav1").put(m.parameter("bridge", 1.0))
        bridge.declare_ready("uav1", "bridge")
        assert bridge.query(keys.COMMAND, "uav1", m.vehicle_command("bridge"), m.COMMAND_ACK,
                            timeout=0.5) is None  # the test's sim does not answer
        wait_for(lambda: len(got) >= 3 and ready, 5.0, "the bridge's inputs and token")
        time.sleep(0.5)  # anything of the tool's that got through would be here by now
        assert sorted(got) == [("cmd_vel", 2.0), ("goal", "bridge"), ("params", "bridge")], got
        assert ready == ["bridge"], ready
        assert [r.msg.command for r in requests.take()] == ["bridge"]
        assert requests.decode_errors == 0
    finally:
        for b in (sim, gcs, bridge):
            b.close()


def test_no_certificate_or_a_wrong_one_cannot_connect(certs, router, tmp_path):
    """Mutual TLS refuses a client with no certificate, another CA's, or one that trusts
    the router but presents another CA's certificate; refusal and a router that is not up
    look the same to a client (a connect timeout), so a certified client first proves,
    through the router, that it is up, and again after the refusals."""
    import json
    from concurrent.futures import ThreadPoolExecutor

    sim, perception = (client(router, str(certs / f"{n}.json5")) for n in ("sim", "perception"))
    seen: list[int] = []
    try:
        sim.subscribe(keys.OBSERVATION, "uav1", lambda msg: seen.append(msg.step))
        pub = perception.publisher(keys.OBSERVATION, "uav1")

        def through_router(step: int) -> None:
            pub.put(m.observation([0.0] * 35, 0.1, step=step))
            wait_for(lambda: step in seen, 5.0, "an observation through the router")

        time.sleep(1.0)  # the subscription reaches the router
        through_router(1)
        other = make_certs(tmp_path / "other", ("sim",))  # a CA the router does not trust
        tls = {"root_ca_certificate": str(certs / "ca.pem")}  # trusts the router
        no_cert, wrong_cert = tmp_path / "no-cert.json5", tmp_path / "wrong-cert.json5"
        no_cert.write_text(json.dumps({"transport": {"link": {"tls": tls}}}))
        wrong_cert.write_text(json.dumps({"transport": {"link": {"tls": {
            **tls, "connect_private_key": str(other / "sim.key.pem"),
            "connect_certificate": str(other / "sim.pem"), "enable_mtls": True}}}}))

        def attempt(config: str | None) -> Exception | None:
            try:
                client(router, config).close()
            except Exception as err:  # noqa: BLE001 - its type is checked below
                return err
            return None  # connected

        configs = (None, str(other / "sim.json5"), str(no_cert), str(wrong_cert))
        with ThreadPoolExecutor(len(configs)) as pool:
            errors = list(pool.map(attempt, configs))
        for config, err in zip(configs, errors, strict=True):
            assert isinstance(err, SessionError), (config, err)
        through_router(2)  # the router was up all along
        client(router, str(certs / "bridge.json5")).close()  # and a new certified one joins
    finally:
        sim.close()
        perception.close()


class RouterProcess:
    """``skyloop router`` as ``skyloop up --router`` starts it (a child program with the
    configuration ``skyloop certs`` wrote), its output read at the end (:meth:`stop`)."""

    def __init__(self, certs, **env: str) -> None:
        import os
        import subprocess
        import sys
        from pathlib import Path

        self.certs, self.endpoint = certs, f"tls/localhost:{free_port()}"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "skyloop", "router", "--listen", self.endpoint,
             "--zenoh-config", str(certs / "router.json5")],
            cwd=Path(__file__).resolve().parents[2],
            env={**{k: v for k, v in os.environ.items() if k != "RUST_LOG"}, **env},
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.sessions: list[Bus] = []

    def client(self, node: str) -> Bus:
        """A client session with ``node``'s certificate (the first one waits for the
        router to listen)."""
        deadline = time.monotonic() + 30.0
        while True:
            try:
                bus = client(self.endpoint, str(self.certs / f"{node}.json5"))
            except SessionError:
                assert self.proc.poll() is None and time.monotonic() < deadline, "no router"
                continue
            self.sessions.append(bus)
            return bus

    def stop(self) -> tuple[str, dict[str, int]]:
        """Close the sessions, SIGTERM the router: what it printed (colours removed) and
        its counters line (``skyloop.launcher.COUNTERS_LINE``)."""
        import json
        import re

        from skyloop.launcher import COUNTERS_LINE

        for bus in self.sessions:
            bus.close()
        self.proc.terminate()
        out = re.sub(r"\x1b\[[0-9;]*m", "", self.proc.communicate(timeout=15)[0])
        assert self.proc.returncode == 0, out[-3000:]
        last = [line for line in out.splitlines() if line.startswith(COUNTERS_LINE)]
        assert len(last) == 1 and out.rstrip().endswith(last[0]), out[-3000:]
        return out, json.loads(last[0][len(COUNTERS_LINE):])


def test_the_router_counts_each_refused_setpoint(certs):
    """An unlisted certificate (``skyloop certs --nodes gcs`` after the router's
    configuration) puts N setpoints on ``cmd_vel`` with a publisher (each one refused from
    the rights Zenoh cached for the key) and M more with ``session.put`` on the key and
    on wildcards (each decided anew), and perception (a listed node: Zenoh decides each
    of its subjects in turn) 2 wildcard puts: the router counts N + M + 2 refusals, the
    sim gets none of them, and the bridge's setpoints, on the same router, arrive and
    count nothing. Without RUST_LOG, none of Zenoh's decisions is shown: only counted."""
    make_certs(certs, ("gcs",))
    router = RouterProcess(certs)
    got: list[float] = []
    try:
        gcs, sim, bridge, perception = (router.client(n)
                                        for n in ("gcs", "sim", "bridge", "perception"))
        perception.publisher(keys.OBSERVATION, "uav1").put(m.observation([0.0] * 35, 0.1))
        # a client sends a put only where a subscriber matches
        sim.subscribe(keys.CMD_VEL, "uav1", lambda msg: got.append(msg.velocity.x))
        time.sleep(1.0)
        n = 25
        pub = gcs.publisher(keys.CMD_VEL, "uav1")
        for i in range(n):
            pub.put(setpoint(1.0))
            if i % 5 == 4:
                bridge.publisher(keys.CMD_VEL, "uav1").put(setpoint(2.0))
        undeclared = ("skyloop/uav1/cmd_vel", "skyloop/**", "skyloop/*/cmd_vel")
        for key in undeclared:
            gcs.session.put(key, m.encode(setpoint(3.0)))
        for _ in range(2):
            perception.session.put("skyloop/**", m.encode(setpoint(4.0)))
        wait_for(lambda: len(got) >= n // 5, 5.0, "the bridge's setpoints")
        time.sleep(0.5)  # anything of the tool's that got through would be here by now
    finally:
        out, counters = router.stop()
    assert got == [2.0] * (n // 5)
    total = n + len(undeclared) + 2
    assert counters == {"denied": total, "denied_put_ingress": total}, counters
    assert f"access control refused {total} message(s): Put (ingress) on " \
           f"skyloop/uav1/cmd_vel {n + 1}, " in out, out[-3000:]
    assert "access_control" not in out, out[-3000:]


def test_the_stack_s_own_traffic_is_refused_nothing(certs):
    """The nodes named in the router's configuration doing what they do (telemetry,
    setpoints, readiness tokens, the commander's queryable and its queries, subscribers
    forwarded to each other): Zenoh decides each subject of a node in turn, refusals
    before an allowance included, and none of it counts."""
    router = RouterProcess(certs)
    got: list[object] = []
    try:
        sim, perception, bridge = (router.client(n) for n in ("sim", "perception", "bridge"))
        sim.subscribe(keys.CMD_VEL, "uav1", lambda msg: got.append(msg.velocity.x))
        bridge.subscribe(keys.OBSERVATION, "uav1", lambda msg: got.append("observation"))
        requests = sim.queryable(keys.COMMAND, "uav1")
        for node, bus in (("sim", sim), ("perception", perception), ("bridge", bridge)):
            bus.declare_ready("uav1", node)
        time.sleep(1.0)
        for _ in range(10):
            bridge.publisher(keys.CMD_VEL, "uav1").put(setpoint(2.0))
            perception.publisher(keys.OBSERVATION, "uav1").put(m.observation([0.0] * 35, 0.1))
        bridge.query(keys.COMMAND, "uav1", m.vehicle_command("bridge"), m.COMMAND_ACK,
                     timeout=0.5)  # the test's sim does not answer
        wait_for(lambda: len(got) >= 20, 5.0, "the setpoints and observations")
        assert [r.msg.command for r in requests.take()] == ["bridge"]
    finally:
        out, counters = router.stop()
    assert counters == {"denied": 0}, (counters, out[-3000:])


def test_the_router_shows_zenoh_s_decisions_with_rust_log(certs):
    """With RUST_LOG naming the access control at TRACE, ``skyloop router`` shows Zenoh's
    decisions as before (the unlisted tool's setpoint refused) and counts them too; with
    another RUST_LOG, what that shows and no decision."""
    make_certs(certs, ("gcs",))
    decision = ("Using cached result: \\w+ is unauthorized to Put \\(ingress\\) on "
                "skyloop/uav1/cmd_vel")
    got: list[float] = []
    for rust_log, shown in (("zenoh::net::routing::interceptor::access_control=trace", True),
                            ("zenoh::net::runtime=info", False)):
        router = RouterProcess(certs, RUST_LOG=rust_log)
        try:
            gcs, sim = router.client("gcs"), router.client("sim")
            sim.subscribe(keys.CMD_VEL, "uav1", lambda msg: got.append(msg.velocity.x))
            time.sleep(1.0)
            gcs.publisher(keys.CMD_VEL, "uav1").put(setpoint(1.0))
            time.sleep(0.5)
        finally:
            out, counters = router.stop()
        assert got == []
        assert counters["denied_put_ingress"] == 1, (rust_log, counters)
        assert bool(re.search(decision, out)) == shown, (rust_log, out[-3000:])
        assert ("zenoh::net::runtime" in out) != shown, (rust_log, out[-3000:])


def test_a_bad_config_file_is_named(tmp_path):
    bad = tmp_path / "bad.json5"
    bad.write_text("{ this is not json5")
    for path, why in ((str(bad), "bad.json5"), (str(tmp_path / "none.json5"), "no such file")):
        with pytest.raises(ValueError, match=why):
            SessionConfig(config_file=path).zenoh_config()


def test_the_stack_flies_on_a_secured_bus(certs, tmp_path):
    """``skyloop up --router --zenoh-config-dir DIR``: the router on a tls endpoint, every
    node with its own certificate, the bridge's setpoints allowed: episodes fly. A tool
    with a later certificate of the CA joins the router once the sim is ready and puts
    setpoints: the summary and ``--json`` count each one refused, and nothing else."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    full = make_certs(tmp_path / "certs")  # every node of a stack, the launcher too
    make_certs(full, ("gcs",))  # router.json5 written without it: a read-only tool
    root = Path(__file__).resolve().parents[2]
    udp = [str(free_port(socket.SOCK_DGRAM)) for _ in range(4)]
    hub = f"tls/localhost:{free_port()}"
    cmd = [sys.executable, "-m", "skyloop", "up", "--router", "--zenoh-config-dir", str(full),
           "--hub", hub, "--episodes", "1", "--policy", "scripted", "--json",
           str(tmp_path / "s.json"), "--api-port", udp[0], "--api-local-port", udp[1],
           "--gcs-port", udp[2], "--gcs-local-port", udp[3]]
    proc = subprocess.Popen(cmd, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    n, ready, gcs = 10, threading.Event(), None
    try:
        deadline = time.monotonic() + 60.0
        while gcs is None:
            try:
                gcs = client(hub, str(full / "gcs.json5"))
            except SessionError:
                assert proc.poll() is None and time.monotonic() < deadline, "no router"
        gcs.watch_ready("uav1", lambda node, alive: node == "sim" and alive and ready.set())
        assert ready.wait(120.0), "the sim never got ready"
        pub = gcs.publisher(keys.CMD_VEL, "uav1")  # the sim subscribes before it is ready
        for _ in range(n):
            pub.put(setpoint(1.0))
            time.sleep(0.01)
    finally:
        if gcs is not None:
            gcs.close()
        out = proc.communicate(timeout=180)[0]
    assert proc.returncode == 0, out
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["episodes"] == 1
    assert summary["counters"]["router"] == {"denied": n, "denied_put_ingress": n}, summary
    assert f"refused by the router's access control: {n} message(s) (put ingress {n})" in out
    no_router = subprocess.run([sys.executable, "-m", "skyloop", "up", "--zenoh-config-dir",
                                str(full)], cwd=root, capture_output=True, text=True, timeout=60)
    assert no_router.returncode == 2 and "needs --router" in no_router.stderr
    partial = subprocess.run([sys.executable, "-m", "skyloop", "up", "--router",
                              "--zenoh-config-dir", str(certs)], cwd=root, capture_output=True,
                             text=True, timeout=60)  # no launcher/policy/... configs there
    assert partial.returncode == 2 and "launcher.json5" in partial.stderr, partial.stderr
