"""The stack's commands (``skyloop sim``, ``perception``, ``policy``, ``bridge``, ``up``)
and the others of ``skyloop.cli.tools`` (``record``, ``router``, ``certs``, ``demo``, ...)
have options generated from their settings dataclasses (``skyloop.cli.stack_settings``,
tyro): every flag they had keeps its name and meaning, ``--help`` shows each default
(the dataclass's) and the choices, and a bad value is one line naming the flag, exit 2,
before anything starts."""

from __future__ import annotations

import re
import socket
import subprocess
import sys
from dataclasses import MISSING, fields
from pathlib import Path

import pytest

from bus.task import TASK
from skyloop.cli.stack import COMMANDS as NODES
from skyloop.cli.stack import parse_node
from skyloop.cli.stack_settings import SimCommand, UpCommand
from skyloop.cli.tools import COMMANDS as TOOLS
from skyloop.cli.tools import parse_tool

COMMANDS = {**NODES, **TOOLS}

BUS = ["--vehicle", "--mode", "--connect", "--listen", "--zenoh-config", "-v", "--verbose"]
CLOCK = ["--lockstep", "--realtime"]
SECURITY = ["--signing-key-file", "--allow-sysid", "--expose"]
PORTS = ["--api-port", "--api-local-port", "--gcs-port", "--gcs-local-port"]
#: every flag each command had when it was hand-written argparse (tests, README, docker
#: compose files and the launcher use them)
FLAGS = {
    "sim": [*BUS, *CLOCK, "--scenario", "--episodes", "--free-flight", "--goals-from-bus",
            "--param", "--lockstep-timeout", "--seed", "--max-steps", "--wait-go"],
    "perception": [*BUS, "--encoding"],
    "policy": [*BUS, *CLOCK, *SECURITY, "--policy", "--api-host", "--api-port",
               "--takeoff-altitude", "--weights-from-bus", "--hold", "--startup-timeout"],
    "bridge": [*BUS, *SECURITY, *PORTS, "--bind", "--api-host", "--gcs-host", "--no-gcs",
               "--command-timeout", "--params-file", "--param"],
    "up": [*CLOCK, *SECURITY, *PORTS, "--scenario", "--episodes", "--seed", "--max-steps",
           "--goals", "--policy", "--router", "--zenoh-config-dir", "--hub", "--log-dir",
           "--log-split-episodes", "--log-split-minutes", "--log-compression", "--json",
           "--vehicle", "--param",
           "--lockstep-timeout", "--restart", "--max-restarts", "--viz", "--viz-scan-every",
           "--encoding", "-v", "--verbose"],
    "demo": ["--scenario", "--episodes", "--seed", "--out-dir", "--policy", "--json"],
    "render": ["--scenario", "--seed", "--out"],
    "bench": ["--quick", "--json", "--only", "--minutes"],
    "view": ["--vehicle", "--viz", "--scan-every", "--web-port", "--grpc-port"],
    "viz": [*BUS, "--scenario", "--viz", "--scan-every", "--web-port", "--grpc-port"],
    "record": ["--scenario", "--out", "--vehicle", "--run-name", "--compression",
               "--split-episodes", "--split-minutes", "--no-ros-view", "--queue", "--mode",
               "--connect", "--listen", "--zenoh-config", "-v", "--verbose"],
    "router": ["--listen", "--zenoh-config"],
    "certs": ["--out", "--nodes", "--host", "--days"],
    "plot": ["--out"],
    "log repair": ["--out"],
    "experiment run": ["--out", "--max-concurrent", "--address", "--cpus-per-trial"],
    "experiment report": ["--eval-episodes"],
}
POSITIONAL = {"log": "LOG", "runs": "RUN", "path": "LOG", "grid": "GRID", "dir": "DIR"}


def parse_any(argv: list[str]):
    """The settings of ``skyloop NAME ARGS`` (``argv[0]`` may be two words)."""
    if argv[0] in NODES:
        return parse_node(argv)
    return parse_tool([*argv[0].split(), *argv[1:]])


def help_entries(text: str) -> dict[str, str]:
    """Each flag (aliases too: ``-v``) -> its help row(s), from tyro's boxed ``--help``."""
    entries: dict[str, str] = {}
    current: list[str] = []
    for line in text.splitlines():
        row = line.strip().strip("│").rstrip()
        start = re.match(r" ((?:-[a-z], )?--[a-z0-9-]+)", row)  # an entry starts one space in
        if start:
            current = start.group(1).split(", ")
            for name in current:
                entries[name] = row
        elif current and row.startswith("  "):
            for name in current:
                entries[name] += " " + row.strip()
        else:
            current = []
    return entries


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


@pytest.fixture(scope="module")
def helps() -> dict[str, str]:
    out = {}
    for name in COMMANDS:
        proc = subprocess.run([sys.executable, "-m", "skyloop", *name.split(), "--help"],
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0 and proc.stderr == "", (name, proc.stderr)
        out[name] = proc.stdout
    return out


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_flag_is_kept_and_help_shows_its_default(helps, name):
    entries = help_entries(helps[name])
    assert helps[name].startswith(f"usage: skyloop {name} ")
    missing = [f for f in FLAGS[name] if f not in entries]
    assert not missing, (name, missing)
    cls = COMMANDS[name][0]
    assert {flag(f.name) for f in fields(cls) if f.name not in POSITIONAL} <= set(entries)
    hints = {"mode": "$SKYLOOP_ZENOH_MODE or peer", "zenoh_config": "$ZENOH_CONFIG",
             "connect": "$SKYLOOP_ZENOH_CONNECT", "listen": "$SKYLOOP_ZENOH_LISTEN",
             "signing_key_file": "$SKYLOOP_MAVLINK_KEY", "lockstep": "(the default)",
             "takeoff_altitude": "MIS_TAKEOFF_ALT", "episodes": "(default: ",
             "hub": "free loopback port", "viz": "no viewer",
             "policy": "(default: the shipped policy)", "only": "every module but soak",
             "minutes": "(default: 60; --quick: 2)", "vehicle": "(default: every one)",
             "scenario": "(default: the first episode's)", "out": "beside the source run",
             "max_concurrent": "CPUs per trial", "address": "$RAY_ADDRESS",
             "cpus_per_trial": "1 for sync trials", "run_name": "run-<date>-<time>-<pid>"}
    for f in fields(cls):
        if f.name in POSITIONAL:
            box = helps[name].split("positional arguments", 1)[1].split("╰", 1)[0]
            assert f"│ {POSITIONAL[f.name]} " in box and "(required)" in box, box
            continue
        entry = entries[flag(f.name)]
        if f.default is MISSING:
            assert entry.endswith("(required)"), entry
        elif f.default == ():  # a repeatable flag: none by default
            assert "(repeatable)" in entry, entry
        elif f.name in hints and f.default is None:
            assert hints[f.name] in entry, entry
        elif f.name == "lockstep":
            assert entry.endswith("(the default)"), entry
        elif isinstance(f.default, tuple):  # several values: as they are typed
            assert entry.endswith(f"(default: {' '.join(f.default)})"), entry
        else:
            shown = re.search(r"\(default: (.*?)\)$", entry)
            assert shown and shown.group(1) == str(f.default), (name, f.name, entry)


def test_help_shows_choices_and_the_defaults_that_live_elsewhere(helps):
    up = help_entries(helps["up"])
    assert "{seeded,gcs}" in up["--goals"] and "{no,on-failure}" in up["--restart"]
    assert "{zstd,lz4,none}" in up["--log-compression"]
    assert "(default: zstd)" in up["--log-compression"]
    assert f"(default: {TASK.max_steps})" in up["--max-steps"]  # the task specification's
    assert "(default: 5;" in up["--episodes"]
    for name in ("sim", "perception", "policy", "bridge"):
        assert "--mode {peer,client}" in help_entries(helps[name])["--mode"]
    bridge = help_entries(helps["bridge"])
    assert ["(default: 14540)" in bridge["--api-port"], "(default: 18570)" in
            bridge["--gcs-local-port"]] == [True, True]


def test_defaults_agree_with_the_configs_they_feed():
    """The sim's defaults are ``SimNodeConfig``'s, the ports the MAVLink configs'."""
    from mavlink_bridge.offboard_client import OffboardClientConfig
    from mavlink_bridge.vehicle_link import VehicleLinkConfig
    from sitl.node.step import SimNodeConfig

    sim, node = SimCommand(), SimNodeConfig()
    assert (sim.scenario, sim.episodes, sim.seed, sim.vehicle, sim.realtime, sim.max_steps,
            sim.free_flight, sim.goals_from_bus, sim.lockstep_timeout, sim.params) == (
        node.scenario, node.episodes, node.seed, node.vehicle, node.realtime, node.max_steps,
        node.free_flight, node.goals_from_bus, node.lockstep_timeout_s, node.params)
    links, up = VehicleLinkConfig(), UpCommand()
    assert links.api is not None and links.gcs is not None
    assert (up.api_port, up.api_local_port, up.gcs_port, up.gcs_local_port) == (
        links.api.remote_port, links.api.local_port, links.gcs.remote_port,
        links.gcs.local_port) == (OffboardClientConfig().listen_port, 14580, 14550, 18570)
    assert parse_node(["policy"]).api_port == up.api_port


BAD = [
    ("sim", ["--episodes", "-1"], "--episodes", "-1"),
    ("sim", ["--max-steps", "0"], "--max-steps", "0"),
    ("sim", ["--seed", "x"], "--seed", "x"),
    ("sim", ["--lockstep-timeout", "0"], "--lockstep-timeout", "0"),
    ("sim", ["--param", "NOPE=1"], "--param", "NOPE"),
    ("sim", ["--param", "COM_OF_LOSS_T"], "--param", "COM_OF_LOSS_T"),
    ("sim", ["--lockstep", "--realtime"], "--realtime", "--lockstep"),
    ("perception", ["--mode", "router"], "--mode", "router"),
    ("perception", ["--vehicle", "a/b"], "--vehicle", "a/b"),
    ("up", ["--vehicle", "uav*"], "--vehicle", "uav*"),
    ("policy", ["--api-port", "70000"], "--api-port", "70000"),
    ("policy", ["--allow-sysid", "x"], "--allow-sysid", "x"),
    ("policy", ["--takeoff-altitude", "-2"], "--takeoff-altitude", "-2"),
    ("policy", ["--startup-timeout", "0"], "--startup-timeout", "0"),
    ("bridge", ["--gcs-port", "0"], "--gcs-port", "0"),
    ("bridge", ["--command-timeout", "-1"], "--command-timeout", "-1"),
    ("bridge", ["--param", "MPC_XY_VEL_MAX=abc"], "--param", "abc"),
    ("up", ["--episodes", "-1"], "--episodes", "-1"),
    ("up", ["--episodes", "x"], "--episodes", "x"),  # int | None: one line too
    ("policy", ["--takeoff-altitude", "high"], "--takeoff-altitude", "high"),
    ("up", ["--episodes", "0"], "--episodes", "0"),
    ("up", ["--max-restarts", "0"], "--max-restarts", "0"),
    ("up", ["--viz-scan-every", "0"], "--viz-scan-every", "0"),
    ("up", ["--log-split-episodes", "-1"], "--log-split-episodes", "-1"),
    ("up", ["--log-split-minutes", "-2"], "--log-split-minutes", "-2"),
    ("up", ["--log-split-minutes", "nan"], "--log-split-minutes", "nan"),
    ("up", ["--goals", "mission"], "--goals", "mission"),
    ("up", ["--restart", "always"], "--restart", "always"),
    ("up", ["--log-compression", "gzip"], "--log-compression", "gzip"),
    ("up", ["--viz", "window"], "--viz", "window"),
    ("up", ["--max-steps", "-300"], "--max-steps", "-300"),
    ("up", ["--zenoh-config-dir", "certs"], "--zenoh-config-dir", "needs --router"),
    ("demo", ["--episodes", "0"], "--episodes", "0"),
    ("demo", ["--seed", "1.5"], "--seed", "1.5"),
    ("render", ["--seed", "x"], "--seed", "x"),
    ("bench", ["--minutes", "0"], "--minutes", "0"),
    ("view", ["run", "--viz", "save:x.png"], "--viz", "save:x.png"),
    ("view", ["run", "--scan-every", "0"], "--scan-every", "0"),
    ("viz", ["--viz", "window"], "--viz", "window"),
    ("viz", ["--grpc-port", "99999"], "--grpc-port", "99999"),
    ("experiment run", ["g.toml", "--out", "o", "--max-concurrent", "0"], "--max-concurrent",
     "0"),
    ("experiment run", ["g.toml", "--out", "o", "--cpus-per-trial", "x"], "--cpus-per-trial",
     "x"),
    ("experiment report", ["d", "--eval-episodes", "-1"], "--eval-episodes", "-1"),
    ("record", ["--split-episodes", "-1"], "--split-episodes", "-1"),
    ("record", ["--split-minutes", "-1"], "--split-minutes", "-1"),
    ("record", ["--split-minutes", "nan"], "--split-minutes", "nan"),
    ("record", ["--split-minutes", "soon"], "--split-minutes", "soon"),
    ("record", ["--queue", "0"], "--queue", "0"),
    ("record", ["--compression", "bogus"], "--compression", "bogus"),
    ("record", ["--vehicle", "a/b"], "--vehicle", "a/b"),
    ("record", ["--mode", "router"], "--mode", "router"),
    ("certs", ["--days", "0"], "--days", "0"),
    ("certs", ["--nodes"], "--nodes", "NAME"),
]


@pytest.mark.parametrize("name, argv, bad_flag, value", BAD)
def test_a_bad_value_is_one_line_naming_the_flag(capsys, name, argv, bad_flag, value):
    with pytest.raises(SystemExit) as exit_:
        parse_any([name, *argv])
    err = capsys.readouterr().err
    assert exit_.value.code == 2
    assert err.count("\n") == 1, err
    assert err.startswith(f"skyloop {name}: error: argument {bad_flag}: "), err
    assert value in err, err


@pytest.mark.parametrize("argv, bad_flag", [
    (["record", "--split-episodes", "-1"], "--split-episodes"),
    (["record", "--split-minutes", "-1"], "--split-minutes"),
    (["certs", "--days", "0"], "--days"),
    (["record", "--compression", "bogus"], "--compression"),
])
def test_record_and_certs_refuse_a_bad_value_in_one_line(tmp_path, argv, bad_flag):
    """Through the ``skyloop`` command, as a user runs it: exit 2, one line naming the
    flag, no traceback, nothing written."""
    proc = subprocess.run([sys.executable, "-m", "skyloop", *argv, "--out",
                           str(tmp_path / "out")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.startswith(f"skyloop {argv[0]}: error: argument {bad_flag}: "), \
        proc.stderr
    assert proc.stdout == "" and not (tmp_path / "out").exists()


def test_router_refuses_a_zenoh_config_it_cannot_read(tmp_path):
    missing = tmp_path / "router.json5"
    proc = subprocess.run([sys.executable, "-m", "skyloop", "router", "--listen",
                           "tcp/127.0.0.1:0", "--zenoh-config", str(missing)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr == f"skyloop router: Zenoh config {missing} (--zenoh-config or " \
                          f"ZENOH_CONFIG): no such file\n", proc.stderr


def test_a_taken_endpoint_is_one_line_naming_it():
    """A router or a node told to listen on a taken port: exit 2, one line naming the
    endpoint and the flags that choose it, no traceback."""
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        endpoint = f"tcp/127.0.0.1:{taken.getsockname()[1]}"
        for argv in (["router", "--listen", endpoint], ["perception", "--listen", endpoint]):
            proc = subprocess.run([sys.executable, "-m", "skyloop", *argv],
                                  capture_output=True, text=True, timeout=120)
            assert proc.returncode == 2, (argv, proc.stderr)
            assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
            assert f"cannot open a Zenoh session: Can not create a new TCP listener bound to " \
                   f"{endpoint}" in proc.stderr and "--listen" in proc.stderr, proc.stderr
            assert ".rs:" not in proc.stderr, proc.stderr  # no Rust source locations


def test_a_policy_with_no_vehicle_exits_with_one_line():
    """``skyloop policy`` with no vehicle on its API port: after --startup-timeout, exit 1
    with one line saying why (no traceback), not a hang or a torch/MAVLink trace."""
    from loopback import free_port

    proc = subprocess.run([sys.executable, "-m", "skyloop", "policy", "--policy", "scripted",
                           "--startup-timeout", "1", "--listen",
                           f"tcp/127.0.0.1:{free_port()}", "--api-port",
                           str(free_port(socket.SOCK_DGRAM))],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.splitlines()[-1] == ("skyloop policy: could not take the vehicle into "
                                            "OFFBOARD: no heartbeat from system 1 within 1 s")


def test_a_bad_value_stops_up_before_anything_starts(tmp_path):
    logs = tmp_path / "logs"
    for argv in (["--episodes", "-1"], ["--param", "SKY_ICO_RADIUS=-3"],
                 ["--viz", "nowhere"]):
        proc = subprocess.run([sys.executable, "-m", "skyloop", "up", "--log-dir", str(logs),
                               *argv], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2, (argv, proc.stderr)
        assert proc.stderr.count("\n") == 1 and proc.stderr.startswith(
            "skyloop up: error: argument "), proc.stderr
        assert proc.stdout == "" and not logs.exists()  # no node started, nothing recorded


def test_command_lines_give_the_settings_they_say():
    sim = parse_node(["sim", "--realtime", "--scenario", "city", "--episodes", "0",
                      "--seed", "7", "--max-steps", "50", "--lockstep-timeout", "0.5",
                      "--param", "COM_OF_LOSS_T=0.5", "--param", "MPC_XY_VEL_MAX=1.5",
                      "--free-flight", "--wait-go", "--vehicle", "uav2", "-v",
                      "--mode", "client", "--connect", "tcp/127.0.0.1:7447"])
    assert (sim.realtime, sim.scenario, sim.episodes, sim.seed, sim.max_steps,
            sim.lockstep_timeout, sim.free_flight, sim.wait_go, sim.vehicle, sim.verbose,
            sim.mode, sim.connect) == (True, "city", 0, 7, 50, 0.5, True, True, "uav2", True,
                                       "client", "tcp/127.0.0.1:7447")
    assert sim.params == {"COM_OF_LOSS_T": 0.5, "MPC_XY_VEL_MAX": 1.5}
    policy = parse_node(["policy", "--policy", "scripted", "--allow-sysid", "245",
                         "--allow-sysid", "255", "--hold", "--takeoff-altitude", "3"])
    assert (policy.actor, policy.allow_sysid, policy.hold, policy.takeoff_altitude,
            policy.realtime) == ("scripted", (245, 255), True, 3.0, False)
    assert parse_node(["policy"]).actor is None  # the shipped actor
    bridge = parse_node(["bridge", "--no-gcs", "--params-file", "none", "--bind", "0.0.0.0",
                         "--expose"])
    assert (bridge.no_gcs, bridge.params_file, bridge.bind, bridge.expose) == (
        True, "none", "0.0.0.0", True)


def test_group_commands_give_the_settings_they_say(capsys):
    run = parse_any(["experiment run", "experiments/x.toml", "--out", "g", "--max-concurrent",
                     "2", "--address", "ray://h:10001", "--cpus-per-trial", "1"])
    assert (run.grid, run.out, run.max_concurrent, run.address, run.cpus_per_trial) == (
        Path("experiments/x.toml"), Path("g"), 2, "ray://h:10001", 1)
    report = parse_any(["experiment report", "g", "--eval-episodes", "10"])
    assert (report.dir, report.eval_episodes) == (Path("g"), 10)
    assert parse_any(["experiment report", "g"]).eval_episodes == 0
    repair = parse_any(["log repair", "run/x.mcap", "--out", "fixed"])
    assert (repair.path, repair.out) == (Path("run/x.mcap"), Path("fixed"))
    plot = parse_any(["plot", "runs/a", "runs/b", "--out", "c.png"])
    assert (plot.runs, plot.out) == ((Path("runs/a"), Path("runs/b")), Path("c.png"))
    for argv, says in ((["plot"], "the following arguments are required: RUN"),
                       (["log repair"], "the following arguments are required: LOG"),
                       (["experiment run", "g.toml"], "the following arguments are required")):
        with pytest.raises(SystemExit) as exit_:
            parse_any(argv)
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and err.count("\n") == 1 and says in err, err
    proc = subprocess.run([sys.executable, "-m", "skyloop", "experiment", "--help"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "run" in proc.stdout and "report" in proc.stdout


def test_tool_command_lines_give_the_settings_they_say():
    demo = parse_tool(["demo", "--scenario", "forest", "--episodes", "2", "--seed", "3",
                       "--out-dir", "o", "--policy", "scripted", "--json", "d.json"])
    assert (demo.scenario, demo.episodes, demo.seed, demo.out_dir, demo.policy,
            demo.json) == ("forest", 2, 3, Path("o"), "scripted", Path("d.json"))
    assert parse_tool(["demo"]).seed == UpCommand().seed == 1000  # the same demo seeds
    bench = parse_tool(["bench", "--quick", "--only", "perception", "lidar", "--minutes", "2"])
    assert (bench.quick, bench.only, bench.minutes) == (True, ["perception", "lidar"], 2.0)
    view = parse_tool(["view", "run", "--viz", "web", "--web-port", "9091"])
    assert (view.log, view.target.kind, view.web_port, view.vehicle) == ("run", "web", 9091,
                                                                         None)
    assert parse_tool(["view", "run"]).target.kind == "spawn"
    assert UpCommand().viz_scan_every == parse_tool(["viz"]).scan_every


def test_record_router_and_certs_give_the_settings_they_say(helps):
    from bus.certs import NODES as CERT_NODES
    from bus.session import HUB

    # what the launcher starts with --log-dir (skyloop.launcher.run_up)
    record = parse_any(["record", "--out", "runs/logs", "--vehicle", "uav2",
                        "--split-episodes", "3", "--compression", "lz4",
                        "--split-minutes", "0.5"])
    assert (record.out, record.vehicle, record.split_episodes, record.compression,
            record.split_minutes) == (Path("runs/logs"), "uav2", 3, "lz4", 0.5)
    record = parse_any(["record", "--run-name", "k", "--no-ros-view", "--queue", "64", "-v",
                        "--mode", "client", "--connect", "tcp/r:7447", "--zenoh-config", "z"])
    assert (record.run_name, record.no_ros_view, record.queue, record.verbose, record.mode,
            record.connect, record.zenoh_config) == ("k", True, 64, True, "client",
                                                     "tcp/r:7447", "z")
    default = parse_any(["record"])
    assert (default.out, default.vehicle, default.compression, default.split_episodes,
            default.split_minutes, default.queue, default.no_ros_view) == (
        Path("logs"), None, "zstd", 0, 0.0, 512, False)
    router = parse_any(["router", "--listen", "tls/0.0.0.0:7447", "--zenoh-config", "r.json5"])
    assert (router.listen, router.zenoh_config) == ("tls/0.0.0.0:7447", "r.json5")
    assert parse_any(["router"]).listen is None  # $SKYLOOP_ZENOH_LISTEN or the hub, at run
    certs = parse_any(["certs", "--out", "c", "--nodes", "router", "sim", "--host", "a",
                       "--host", "b", "--days", "30"])
    assert (certs.out, certs.nodes, certs.host, certs.days) == (
        Path("c"), ("router", "sim"), ("a", "b"), 30)
    assert parse_any(["certs"]).nodes == CERT_NODES
    record_help, router_help, certs_help = (help_entries(helps[n])
                                            for n in ("record", "router", "certs"))
    assert "{zstd,lz4,none}" in record_help["--compression"]
    assert "4.8 MB an episode with zstd" in record_help["--compression"]
    assert record_help["--compression"].endswith("(default: zstd)")
    assert record_help["--out"].endswith("(default: logs)")
    assert "(default: every one)" in record_help["--vehicle"]
    assert "--mode {peer,client}" in record_help["--mode"]
    assert f"(default: $SKYLOOP_ZENOH_LISTEN or {HUB})" in router_help["--listen"]
    assert "(default: $ZENOH_CONFIG)" in router_help["--zenoh-config"]
    assert certs_help["--nodes"].endswith(f"(default: {' '.join(CERT_NODES)})")
    assert certs_help["--days"].endswith("(default: 825)")
    assert certs_help["--out"].endswith("(default: certs)")
    assert "(repeatable)" in certs_help["--host"]
    listed = subprocess.run([sys.executable, "-m", "skyloop", "--help"], capture_output=True,
                            text=True, timeout=120).stdout
    for name in ("record", "router", "certs"):
        assert re.search(rf"^    {name} +\S", listed, re.M), listed  # with its help text


def test_a_bare_viz_means_spawn():
    assert parse_node(["up"]).viz is None
    assert parse_node(["up", "--viz"]).viz == "spawn"
    bare = parse_node(["up", "--viz", "--router"])
    assert (bare.viz, bare.router) == ("spawn", True)
    assert parse_node(["up", "--viz", "save:run.rrd"]).viz == "save:run.rrd"


def test_the_launcher_hands_each_node_what_up_was_given():
    from skyloop.launcher import _node_args, nodes_of

    up = parse_node(["up", "--realtime", "--scenario", "forest", "--episodes", "3",
                     "--seed", "9", "--max-steps", "120", "--lockstep-timeout", "1.5",
                     "--param", "COM_OF_LOSS_T=0.5", "--vehicle", "uav7", "--goals", "gcs",
                     "--policy", "scripted", "--viz", "web", "--viz-scan-every", "2"]).resolved()
    nodes = {name: parse_any(argv) for name, argv in _node_args(up, {
        "api": 1, "api_local": 2, "gcs": 3, "gcs_local": 4}).items()}
    viz = nodes.pop("viz")
    assert (viz.viz, viz.scan_every, viz.scenario, viz.vehicle) == ("web", 2, "forest", "uav7")
    sim, policy, bridge = nodes["sim"], nodes["policy"], nodes["bridge"]
    assert (sim.scenario, sim.episodes, sim.seed, sim.max_steps, sim.lockstep_timeout,
            sim.realtime, sim.goals_from_bus, sim.param) == (
        "forest", 3, 9, 120, 1.5, True, True, ("COM_OF_LOSS_T=0.5",))
    assert {n.vehicle for n in nodes.values()} == {"uav7"}
    assert (policy.policy, policy.hold, policy.realtime, policy.api_port) == (
        "scripted", True, True, 1)
    assert (bridge.api_port, bridge.api_local_port, bridge.gcs_port, bridge.gcs_local_port,
            bridge.param) == (1, 2, 3, 4, ("COM_OF_LOSS_T=0.5",))
    lockstep = _node_args(parse_node(["up"]).resolved(), {"api": 1, "api_local": 2, "gcs": 3,
                                               "gcs_local": 4})
    assert not parse_node(lockstep["sim"]).realtime and parse_node(lockstep["sim"]).lockstep
    assert parse_node(lockstep["sim"]).episodes == 5
    free = parse_node(["up", "--policy", "none"]).resolved()
    assert (free.episodes, free.realtime, free.lockstep) == (0, True, False)
    assert "policy" not in nodes_of(free) and "--free-flight" in _node_args(free, {
        "api": 1, "api_local": 2, "gcs": 3, "gcs_local": 4})["sim"]


def test_other_compose_files_parse():
    """The vehicle and companion compose files start nodes with flags that parse."""
    import yaml

    docker = Path(__file__).resolve().parents[2] / "docker"
    seen = set()
    for path in sorted(docker.glob("compose*.yaml")):
        for service in (yaml.safe_load(path.read_text()) or {}).get("services", {}).values():
            command = [re.sub(r"\$\{[A-Z0-9_]+:-([^}]*)\}", r"\1", str(a))
                       for a in (service or {}).get("command") or []]
            if command and command[0] in COMMANDS:
                parse_any(command)
                seen.add(command[0])
    assert {"sim", "perception", "policy", "bridge", "record", "router"} <= seen


# ----------------------------------------------------------------------------- learner
LEARNER_FLAGS = ["--vehicles", "--algo", "--reward", "--out", "--seed", "--updates-per-step",
                 "--warmup", "--critic-warmup", "--publish-every", "--checkpoint-every",
                 "--init-actor", "--buffer-size", "--max-episodes", "--grace", "--threads",
                 "--resume", "--no-progress", "--mode", "--connect", "--listen",
                 "--zenoh-config", "-v", "--verbose"]


def test_learner_options_come_from_its_config():
    from policy.nodes.learner import ALGOS, REWARDS, LearnerConfig

    proc = subprocess.run([sys.executable, "-m", "skyloop", "learner", "--help"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    entries = help_entries(proc.stdout)
    assert [f for f in LEARNER_FLAGS if f not in entries] == []
    assert "--queue-size" not in entries  # not a flag
    names = {"grace_s": "--grace"}
    for f in fields(LearnerConfig):
        if f.name == "queue_size":
            continue
        default = f.default_factory() if f.name == "vehicles" else f.default
        shown = re.search(r"\(default: (.*?)\)$", entries[names.get(f.name, flag(f.name))])
        assert shown and shown.group(1) in (str(default), "'*'"), (f.name, shown)
    assert "{td3,ddpg}" in entries["--algo"] and "{tr,ngr,egr,abr}" in entries["--reward"]
    assert set(ALGOS) == {"td3", "ddpg"} and set(REWARDS) == {"tr", "ngr", "egr", "abr"}
    assert "(required)" in entries["--out"]


def test_a_learner_command_line_gives_the_config_it_says(capsys):
    from policy.nodes.learner import LearnerConfig
    from skyloop.cli.learner import parse_learner

    command = parse_learner(["--vehicles", "uav1", "uav2", "--algo", "ddpg", "--reward", "egr",
                             "--out", "runs/l", "--seed", "3", "--updates-per-step", "0.5",
                             "--warmup", "10", "--critic-warmup", "0", "--publish-every", "2",
                             "--checkpoint-every", "5", "--init-actor", "scratch",
                             "--buffer-size", "100", "--max-episodes", "4", "--grace", "0.5",
                             "--threads", "2", "--resume", "--no-progress", "-v",
                             "--mode", "client", "--connect", "tcp/127.0.0.1:7447"])
    assert command.config == LearnerConfig(
        vehicles=["uav1", "uav2"], algo="ddpg", reward="egr", seed=3, updates_per_step=0.5,
        warmup=10, critic_warmup=0, publish_every=2, checkpoint_every=5,
        init_actor="scratch", buffer_size=100, max_episodes=4, grace_s=0.5, threads=2,
        resume=True)
    assert (command.out, command.no_progress, command.verbose, command.mode,
            command.connect) == (Path("runs/l"), True, True, "client", "tcp/127.0.0.1:7447")
    assert parse_learner(["--out", "o"]).config == LearnerConfig()
    for argv, says in ((["--warmup", "-1"], "argument --warmup: must be 0 or more, got -1"),
                       (["--publish-every", "0"], "argument --publish-every: must be at least"),
                       (["--grace", "-1"], "argument --grace: "),
                       (["--updates-per-step", "nan"], "argument --updates-per-step: "),
                       (["--algo", "ppo"], "argument --algo: invalid choice: 'ppo'"),
                       (["--reward", "x"], "argument --reward: invalid choice: 'x'"),
                       (["--mode", "x"],  # an optional choice: None is not offered
                        "argument --mode: invalid choice: 'x' (choose from 'client', 'peer')\n"),
                       (["--vehicles", "*", "uav1"], "argument --vehicles: '*'"),
                       (["--vehicles", "a/b"], "argument --vehicles: vehicle must match"),
                       (["--threads", "x"], "argument --threads: ")):
        with pytest.raises(SystemExit) as exit_:
            parse_learner([*argv, "--out", "unused"])
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and err.count("\n") == 1, (argv, err)
        assert err.startswith(f"skyloop learner: error: {says}"), err
    with pytest.raises(SystemExit):
        parse_learner([])
    assert "the following arguments are required: --out" in capsys.readouterr().err


# ----------------------------------------------------------------------------- health
def test_health_options_and_the_compose_health_checks(capsys):
    """``python -m skyloop.health``: generated options; a bare ``--router`` is the
    default endpoint (""), as the compose files' health checks use it."""
    import socket

    import yaml

    from skyloop.health import HealthCommand, main, parse_health

    proc = subprocess.run([sys.executable, "-m", "skyloop.health", "--help"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    entries = help_entries(proc.stdout)
    for name in ("--router", "--session", "--udp", "--ready", "--publishing", "--vehicle",
                 "--timeout"):
        assert name in entries, name
    assert "(default: 3.0)" in entries["--timeout"] and "(default: uav1)" in entries["--vehicle"]
    assert "$SKYLOOP_ZENOH_CONNECT" in entries["--router"]
    assert parse_health(["--router"]).router == ""
    assert parse_health(["--router", "--ready", "policy"]) == HealthCommand(
        router="", ready=("policy",))
    assert parse_health(["--router", "tcp/r:7447", "--udp", "1", "--udp", "2"]) == \
        HealthCommand(router="tcp/r:7447", udp=(1, 2))
    docker = Path(__file__).resolve().parents[2] / "docker"
    checks = [service["healthcheck"]["test"][4:] for path in docker.glob("compose*.yaml")
              for service in ((yaml.safe_load(path.read_text()) or {}).get("services") or {}
                              ).values() if service and "healthcheck" in service]
    assert len(checks) >= 10
    for argv in checks:
        parse_health([re.sub(r"\$\{[A-Z0-9_]+:-([^}]*)\}", r"\1", str(a)) for a in argv])
    for argv, says in (([], "nothing to check"), (["--udp", "0"], "argument --udp: "),
                       (["--session", "--timeout", "0"], "argument --timeout: "),
                       (["--ready", "policy", "--vehicle", "a/b"], "argument --vehicle: ")):
        with pytest.raises(SystemExit) as exit_:
            parse_health(argv)
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and err.count("\n") == 1, (argv, err)
        assert err.startswith(f"skyloop health: error: {says}"), err
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp, socket.socket() as tcp:
        udp.bind(("127.0.0.1", 0))
        tcp.bind(("127.0.0.1", 0))
        tcp.listen()
        endpoint = f"tcp/127.0.0.1:{tcp.getsockname()[1]}"
        assert main(["--router", endpoint, "--udp", str(udp.getsockname()[1])]) == 0
        assert capsys.readouterr().out.startswith("healthy: ")
