"""``skyloop demo``, ``render``, ``bench``, ``view``, ``viz``, ``record``, ``router``,
``certs``, ``plot``, ``log repair`` and ``experiment run|report``: their options generated
from the dataclasses here with tyro (``skyloop.cli.dataclass_cli.parse``), as the stack's
commands are (``skyloop.cli.stack_settings``): each default once, ``--help`` with choices and
defaults, a bad value one line naming the flag (exit 2) before anything starts. What
each runs is imported only when it runs, so ``--help`` stays light."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import tyro

from bus.certs import DAYS, NODES
from bus.session import ENV_CONFIG, ENV_LISTEN, HUB
from policy.training.settings import ConfigError
from skyloop.cli.dataclass_cli import parse
from skyloop.cli.settings_base import Repeated, minutes_or_off
from skyloop.cli.stack_settings import (
    DEMO_SEED,
    BusFlags,
    ScenarioFlag,
    Settings,
    ViewFlags,
    ZenohFlags,
    at_least,
)

__all__ = ["COMMANDS", "BenchCommand", "CertsCommand", "DemoCommand",
           "ExperimentReportCommand", "ExperimentRunCommand", "LogRepairCommand",
           "PlotCommand", "RecordCommand", "RenderCommand", "RouterCommand", "ViewCommand",
           "VizCommand", "command_of", "parse_tool", "run_tool"]


@dataclass(kw_only=True)
class DemoCommand(ScenarioFlag):
    """``skyloop demo``: fly a controller through a scenario in the in-process env."""

    episodes: Annotated[int, tyro.conf.arg(metavar="N")] = 5
    """episodes to fly (each controller)"""
    seed: int = DEMO_SEED
    """episode i uses seed + i"""
    out_dir: Annotated[Path, tyro.conf.arg(metavar="DIR")] = Path("out")
    """where the picture of the paths goes"""
    policy: Annotated[str | None, tyro.conf.arg(
        metavar="ACTOR|scripted|shipped[:NAME]",
        help_behavior_hint="(default: the shipped policy)")] = None
    """actor file, 'scripted', or a shipped policy by name"""
    json: Annotated[Path | None, tyro.conf.arg(metavar="PATH")] = None
    """write the summary as JSON here"""

    def validate(self) -> None:
        super().validate()
        at_least(self, "episodes", 1)
        if self.policy is not None:
            from policy.shipped import policy_path

            policy_path(self.policy)  # an unknown shipped:NAME names --policy


@dataclass(kw_only=True)
class RenderCommand(ScenarioFlag):
    """``skyloop render``: draw a scenario."""

    seed: int = 0
    """the start and goal drawn with this seed"""
    out: Annotated[Path, tyro.conf.arg(metavar="PNG")] = Path("out/scenario.png")
    """the picture"""


@dataclass(kw_only=True)
class BenchCommand(Settings):
    """``skyloop bench``: speed against peers."""

    quick: bool = False
    """a short run (under 45 s)"""
    json: Annotated[Path | None, tyro.conf.arg(metavar="PATH")] = None
    """write the results as JSON here"""
    only: Annotated[list[str] | None, tyro.conf.arg(
        metavar="NAME [NAME ...]", help_behavior_hint="(default: every module but soak)")] = None
    """run only these benchmark modules ('soak' runs only when named)"""
    minutes: Annotated[float | None, tyro.conf.arg(
        metavar="MIN", help_behavior_hint="(default: 60; --quick: 2)")] = None
    """with --only soak: how long the stack runs"""

    def validate(self) -> None:
        super().validate()
        if self.minutes is not None and not (math.isfinite(self.minutes)
                                             and self.minutes > 0):
            raise ConfigError("minutes", f"must be a finite number above 0, got "
                                         f"{self.minutes}")


@dataclass(kw_only=True)
class ViewCommand(ViewFlags):
    """``skyloop view LOG``: a recorded run in 3D."""

    log: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="LOG")]
    """an .mcap file or a run directory (skyloop up --log-dir)"""
    vehicle: Annotated[str | None, tyro.conf.arg(
        help_behavior_hint="(default: every one)")] = None
    """draw one vehicle"""


@dataclass(kw_only=True)
class WorldFirstFlag:
    """The scenario of the run, for a node that draws its world (``viz``, ``record``)."""

    scenario: Annotated[str | None, tyro.conf.arg(
        metavar="NAME", help_behavior_hint="(default: the first episode's)")] = None
    """build this scenario's world ahead of the first episode (skyloop up passes its
    own; a short run on a loaded machine can end before a world built at its start)"""


@dataclass(kw_only=True)
class VizCommand(WorldFirstFlag, ViewFlags, BusFlags):
    """``skyloop viz``: the live view node of one vehicle."""


@dataclass(kw_only=True)
class RecordCommand(WorldFirstFlag, ZenohFlags):
    """``skyloop record``: the recorder (``bus.log.record.run_record``)."""

    out: Annotated[Path, tyro.conf.arg(metavar="DIR")] = Path("logs")
    """directory for run directories"""
    vehicle: Annotated[str | None, tyro.conf.arg(
        metavar="VEHICLE", help_behavior_hint="(default: every one)")] = None
    """record one vehicle"""
    run_name: Annotated[str | None, tyro.conf.arg(
        metavar="NAME", help_behavior_hint="(default: run-<date>-<time>-<pid>)")] = None
    """run directory name"""
    compression: Annotated[Literal["zstd", "lz4", "none"], tyro.conf.arg(help=(
        "MCAP chunk compression (zstd at bus.log.writer.ZSTD_LEVEL). Measured on real VLP-16 "
        "scans of the stack (XYZIR, 4.5 m range), 100-step episodes: 4.8 MB an episode "
        "with zstd, 6.0 with lz4, 7.9 with none; the recorder took ~1,700 scans/s with "
        "zstd and ~2,900 with none flat out (one run each on a loaded 2-core machine; "
        "`skyloop bench --only record`, benchmarks/RESULTS.md 2026-12-03)"))] = "zstd"
    split_episodes: Annotated[int, tyro.conf.arg(metavar="N")] = 0
    """a new MCAP file of the run every N episodes, never inside one (0: one file)"""
    split_minutes: Annotated[float, tyro.conf.arg(metavar="M", help=(
        "a new MCAP file of the run at the first episode end after M minutes of wall time "
        "in the current file, never inside an episode (as rosbag2's max-bag-duration; "
        "0: off; with --split-episodes, whichever comes first)"))] = 0.0
    no_ros_view: Annotated[bool, tyro.conf.arg(help=(
        "only the bus messages: no TF, /clock, world, goal, path or icosahedron topics for "
        "Foxglove and RViz"))] = False
    queue: Annotated[int, tyro.conf.arg(metavar="N")] = 512
    """messages buffered between Zenoh and the writer"""
    def validate(self) -> None:
        super().validate()
        at_least(self, "split_episodes", 0)
        minutes_or_off(self, "split_minutes")
        at_least(self, "queue", 1)
        if self.vehicle is not None:
            from bus.keys import check_vehicle

            try:
                check_vehicle(self.vehicle)
            except ValueError as err:
                raise ConfigError("vehicle", str(err)) from None


@dataclass(kw_only=True)
class RouterCommand(Settings):
    """``skyloop router``: a Zenoh router in this process (``bus.session.run_router``)."""

    listen: Annotated[str | None, tyro.conf.arg(
        metavar="ENDPOINTS", help_behavior_hint=f"(default: ${ENV_LISTEN} or {HUB})")] = None
    """endpoints, comma-separated (tcp/0.0.0.0:7447 accepts other hosts)"""
    zenoh_config: Annotated[str | None, tyro.conf.arg(
        metavar="FILE", help_behavior_hint=f"(default: ${ENV_CONFIG})")] = None
    """a Zenoh configuration file: TLS certificates, access control (skyloop certs)"""


@dataclass(kw_only=True)
class CertsCommand(Settings):
    """``skyloop certs``: a CA, node certificates and Zenoh configs (``bus.certs``)."""

    out: Annotated[Path, tyro.conf.arg(metavar="DIR")] = Path("certs")
    """where the CA, the certificates and the Zenoh configs go"""
    nodes: Annotated[tuple[str, ...], tyro.conf.arg(metavar="NAME [NAME ...]")] = NODES
    """one certificate (and Zenoh config) each"""
    host: Annotated[tuple[str, ...], Repeated, tyro.conf.arg(metavar="NAME")] = ()
    """another DNS name the router is reached by"""
    days: Annotated[int, tyro.conf.arg(metavar="N")] = DAYS
    """how long the CA and the certificates are valid"""

    def validate(self) -> None:
        super().validate()
        if not self.nodes:
            raise ConfigError("nodes", "expected at least one NAME")
        at_least(self, "days", 1)


@dataclass(kw_only=True)
class PlotCommand(Settings):
    """``skyloop plot RUN [RUN ...]``: success/collision curves of training runs."""

    runs: Annotated[tuple[Path, ...], tyro.conf.Positional, tyro.conf.arg(
        metavar="RUN", help_behavior_hint="(required)")]
    """run directories"""
    out: Annotated[Path, tyro.conf.arg(metavar="PNG")] = Path("out/curves.png")
    """the picture"""

    def validate(self) -> None:
        super().validate()
        if not self.runs:
            raise ValueError("the following arguments are required: RUN")


@dataclass(kw_only=True)
class LogRepairCommand(Settings):
    """``skyloop log repair LOG``: an indexed, finished copy of a log whose writer died."""

    path: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="LOG")]
    """the .mcap file or its run directory"""
    out: Annotated[Path | None, tyro.conf.arg(metavar="DIR", help_behavior_hint=(
        "(default: beside the source run, named <run>-recovered)"))] = None
    """where the copy's run directory goes"""


@dataclass(kw_only=True)
class ExperimentRunCommand(Settings):
    """``skyloop experiment run GRID``: run or continue a grid of training runs."""

    grid: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="GRID")]
    """grid file (TOML), e.g. experiments/paper_static.toml"""
    out: Annotated[Path, tyro.conf.arg(metavar="DIR")]
    """grid directory: one run directory per trial"""
    max_concurrent: Annotated[int | None, tyro.conf.arg(
        metavar="N", help_behavior_hint="(default: the cluster's CPUs per trial)")] = None
    """at most N trials at once"""
    address: Annotated[str | None, tyro.conf.arg(
        metavar="RAY", help_behavior_hint="(default: $RAY_ADDRESS, or an embedded Ray on "
        "this machine)")] = None
    """an existing Ray cluster"""
    cpus_per_trial: Annotated[int | None, tyro.conf.arg(
        metavar="N", help_behavior_hint="(default: 1 for sync trials, 2 for parallel ones: "
        "learner and collector)")] = None
    """CPUs Ray reserves for each trial"""

    def validate(self) -> None:
        super().validate()
        at_least(self, "max_concurrent", 1)
        at_least(self, "cpus_per_trial", 1)


@dataclass(kw_only=True)
class ExperimentReportCommand(Settings):
    """``skyloop experiment report DIR``: REPORT.md, summary.json and figures."""

    dir: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DIR")]
    """grid directory written by 'skyloop experiment run'"""
    eval_episodes: Annotated[int, tyro.conf.arg(metavar="N")] = 0
    """evaluate each final actor on N held-out episodes"""

    def validate(self) -> None:
        super().validate()
        at_least(self, "eval_episodes", 0)


# ----------------------------------------------------------------------------- runs
def run_demo(args: DemoCommand) -> int:
    from skyloop.demo import run_demo as demo

    summary = demo(args.scenario, args.episodes, args.seed, args.out_dir, policy=args.policy)
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2))
    return 0


def run_render(args: RenderCommand) -> int:
    from skyloop.render import render_scenario

    path = render_scenario(args.scenario, args.seed, args.out)
    print(f"wrote {path}")
    return 0


def run_bench(args: BenchCommand) -> int:
    from skyloop.bench import run_bench as bench

    bench(quick=args.quick, json_path=args.json, only=args.only, minutes=args.minutes)
    return 0


def run_view(args: ViewCommand) -> int:
    from skyloop.signals import stop_on_sigterm
    from skyloop.viewer import view_log

    stop_on_sigterm()
    view_log(args.log, args.target, vehicle=args.vehicle, scan_every=args.scan_every,
             web_port=args.web_port, grpc_port=args.grpc_port)
    return 0


def run_viz(args: VizCommand) -> int:
    import logging
    import threading

    from bus.session import SessionConfig
    from skyloop.signals import stop_on_sigterm
    from skyloop.viewer import run_live

    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    stop_on_sigterm()
    cfg = SessionConfig.from_flags(args.mode, args.connect, args.listen, args.zenoh_config)
    c = run_live(args.vehicle, args.target, threading.Event(), session_config=cfg,
                 scan_every=args.scan_every, web_port=args.web_port, grpc_port=args.grpc_port,
                 scenario=args.scenario)
    print(f"viz: drew {c['messages']} messages, {c['scans_drawn']} scans; dropped "
          f"{c['dropped']}", flush=True)
    return 0


def run_record(args: RecordCommand) -> int:
    """Record until SIGINT/SIGTERM, then print where the log is and its counters."""
    import logging

    from bus.log.record import run_record as record
    from bus.session import SessionConfig
    from skyloop.launcher import counters_line
    from skyloop.signals import stop_flag_on_signals

    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    cfg = SessionConfig.from_flags(args.mode, args.connect, args.listen, args.zenoh_config)
    stop = stop_flag_on_signals()
    result = record(args.out, cfg, stop, vehicle=args.vehicle, run_name=args.run_name,
                    compression=args.compression, queue_size=args.queue,
                    split_episodes=args.split_episodes, split_minutes=args.split_minutes,
                    ros_view=not args.no_ros_view,
                    scenario=args.scenario)
    c = result.counters
    print(f"recorded {c['written']} messages ({c['episodes_ended']} episodes ended) into "
          f"{result.path}; dropped {c['dropped']}, undecodable {c['undecodable']}, "
          f"unknown topic {c['unknown_topic']}, write errors {c['write_errors']}; "
          f"derived {c['derived']} (TF, clock, markers, path), view errors "
          f"{c['view_errors'] + c.get('scene_errors', 0)}",
          flush=True)
    print(counters_line({k: v for k, v in c.items() if isinstance(v, int)}), flush=True)
    return 0


def run_router(args: RouterCommand) -> int:
    """Run the Python Zenoh router until SIGINT/SIGTERM; a config it cannot use (an
    unreadable ``--zenoh-config``) is one line, exit 2. With access control in its
    configuration (``skyloop certs``' ``router.json5``) it counts the messages that
    refuses (``bus.denials``: Zenoh's own log, its stdout, read in-process; what
    ``RUST_LOG`` asks for is still shown) and ends with a line of them, if any, and
    its counters line (``skyloop.launcher.COUNTERS_LINE``: ``denied``,
    ``denied_<kind>_<direction>``)."""
    import logging
    import os
    import sys

    from bus.denials import Denials, StdoutTap, merged_filter, target_level
    from bus.session import SessionConfig
    from bus.session import run_router as router
    from skyloop.launcher import counters_line
    from skyloop.signals import stop_flag_on_signals

    listen = args.listen if args.listen is not None else os.environ.get(ENV_LISTEN) or HUB
    config = (args.zenoh_config if args.zenoh_config is not None
              else os.environ.get(ENV_CONFIG) or None)
    cfg = SessionConfig(mode="router", config_file=config)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    import zenoh

    stop = stop_flag_on_signals()
    try:
        acl = cfg.zenoh_config().get_json("access_control/enabled") == "true"
    except ValueError as err:
        print(f"skyloop router: {err}", file=sys.stderr)
        return 2
    tap = None
    if acl:  # count what it refuses (bus.denials): its log read from before Zenoh's starts
        tap = StdoutTap(Denials(), target_level(os.environ.get("RUST_LOG")))
        os.environ["RUST_LOG"] = merged_filter(os.environ.get("RUST_LOG"))
        tap.start()
    zenoh.try_init_log_from_env()  # Zenoh's log (on stdout) as RUST_LOG says
    try:
        router(listen, stop, cfg)
    except ValueError as err:
        print(f"skyloop router: {err}", file=sys.stderr)
        return 2
    finally:
        if tap is not None:
            tap.stop()
            if tap.denials.total:
                print(f"skyloop router: {tap.denials.summary()}", flush=True)
            print(counters_line(tap.denials.counters()), flush=True)
    return 0


def run_certs(args: CertsCommand) -> int:
    from bus.certs import make_certs

    out = make_certs(args.out, args.nodes, args.host, args.days)
    print(f"wrote a CA, {len(args.nodes)} certificates and Zenoh configs into {out}; e.g. "
          f"skyloop router --listen tls/localhost:7447 --zenoh-config {out}/router.json5, "
          f"nodes: --mode client --connect tls/localhost:7447 --zenoh-config "
          f"{out}/<node>.json5")
    return 0


def run_plot(args: PlotCommand) -> int:
    from policy.training.plots import plot_runs

    print(f"wrote {plot_runs(list(args.runs), args.out)}")
    return 0


def run_log_repair(args: LogRepairCommand) -> int:
    from bus.log.writer import recover_log

    if not args.path.exists():
        raise FileNotFoundError(f"{args.path}: no such log file or run directory")
    out, report = recover_log(args.path, args.out)
    print(f"repaired: {out} ({report.summary()})")
    return 0


def run_experiment(args: ExperimentRunCommand) -> int:
    from skyloop.experiment.grid import load_grid
    from skyloop.experiment.run import run_grid

    grid = load_grid(args.grid)  # every error before anything starts
    status = run_grid(grid, args.out, max_concurrent=args.max_concurrent,
                      address=args.address, cpus_per_trial=args.cpus_per_trial)
    return 0 if all(s == "finished" for s in status.values()) else 1


def run_experiment_report(args: ExperimentReportCommand) -> int:
    from skyloop.experiment.report import write_report

    for path in write_report(args.dir, eval_episodes=args.eval_episodes):
        print(f"wrote {path}")
    return 0


#: name -> (settings dataclass, what runs it, one line of help); a name of two words is
#: a command of a group (``skyloop experiment run``)
COMMANDS: dict[str, tuple[type, Callable[[Any], int], str]] = {
    "demo": (DemoCommand, run_demo, "fly a controller through a scenario, print a summary"),
    "render": (RenderCommand, run_render,
               "draw a scenario: terrain, start/goal, a scan, faces"),
    "bench": (BenchCommand, run_bench,
              "measure speed against peers; prints a table, writes JSON"),
    "view": (ViewCommand, run_view, "show a recorded run in 3D (Rerun)"),
    "viz": (VizCommand, run_viz, "live 3D view node (Rerun) of one vehicle on the bus"),
    "record": (RecordCommand, run_record,
               "record every skyloop topic on the bus into MCAP, a run directory each (ROS 2 "
               "schemas, rosbag2 metadata.yaml)"),
    "router": (RouterCommand, run_router,
               "a Zenoh router in this Python process (no zenohd needed); nodes reach it in "
               "client mode"),
    "certs": (CertsCommand, run_certs,
              "a CA, node certificates and Zenoh configs for a bus with mutual TLS and "
              "access control"),
    "plot": (PlotCommand, run_plot, "success/collision curves of one or more training runs"),
    "log repair": (LogRepairCommand, run_log_repair,
                   "write an indexed, finished copy of a log whose writer died (SIGKILL, "
                   "power loss)"),
    "experiment run": (ExperimentRunCommand, run_experiment,
                       "run or continue a grid (finished trials are skipped)"),
    "experiment report": (ExperimentReportCommand, run_experiment_report,
                          "REPORT.md, summary.json and figures of a grid"),
}


def command_of(argv: Sequence[str]) -> tuple[str, list[str]] | None:
    """``(name, rest)`` when ``argv`` starts with a name of :data:`COMMANDS` (of one
    word, or two: ``experiment run``), else None."""
    if len(argv) >= 2 and f"{argv[0]} {argv[1]}" in COMMANDS:
        return f"{argv[0]} {argv[1]}", list(argv[2:])
    if argv and argv[0] in COMMANDS:
        return argv[0], list(argv[1:])
    return None


def parse_tool(argv: Sequence[str]) -> Any:
    """The settings of ``skyloop NAME ARGS`` (``argv`` = [*NAME, *ARGS]); ``--help``
    exits 0, a bad command line exits 2 with one line."""
    found = command_of(argv)
    assert found is not None, argv
    name, rest = found
    cls, _, description = COMMANDS[name]
    return parse(cls, rest, prog=f"skyloop {name}", description=description)


def run_tool(name: str, argv: Sequence[str]) -> int:
    """``skyloop NAME ARGS``: parse (exit 2 on a bad value), run."""
    return COMMANDS[name][1](parse_tool([*name.split(), *argv]))
