"""``skyloop demo``, ``render``, ``bench``, ``view`` and ``viz``: their options generated
from the dataclasses here with tyro (``skyloop.dataclass_cli.parse``), as the stack's
commands are (``skyloop.stack_settings``): each default once, ``--help`` with choices and
defaults, a bad value one line naming the flag (exit 2) before anything starts. What
each runs is imported only when it runs, so ``--help`` stays light."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import tyro

from policy.settings import ConfigError
from skyloop.dataclass_cli import parse
from skyloop.stack_settings import (
    DEMO_SEED,
    BusFlags,
    ScenarioFlag,
    Settings,
    ViewFlags,
    at_least,
)

__all__ = ["COMMANDS", "BenchCommand", "DemoCommand", "RenderCommand", "ViewCommand",
           "VizCommand", "parse_tool", "run_tool"]


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
        metavar="ACTOR|scripted", help_behavior_hint="(default: the shipped policy)")] = None
    """actor file or 'scripted'"""
    json: Annotated[Path | None, tyro.conf.arg(metavar="PATH")] = None
    """write the summary as JSON here"""

    def validate(self) -> None:
        super().validate()
        at_least(self, "episodes", 1)


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
class VizCommand(ViewFlags, BusFlags):
    """``skyloop viz``: the live view node of one vehicle."""

    scenario: Annotated[str | None, tyro.conf.arg(
        help_behavior_hint="(default: the first episode's)")] = None
    """build this scenario's world before declaring ready (skyloop up passes its own)"""


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


#: name -> (settings dataclass, what runs it, one line of help)
COMMANDS: dict[str, tuple[type, Callable[[Any], int], str]] = {
    "demo": (DemoCommand, run_demo, "fly a controller through a scenario, print a summary"),
    "render": (RenderCommand, run_render,
               "draw a scenario: terrain, start/goal, a scan, faces"),
    "bench": (BenchCommand, run_bench,
              "measure speed against peers; prints a table, writes JSON"),
    "view": (ViewCommand, run_view, "show a recorded run in 3D (Rerun)"),
    "viz": (VizCommand, run_viz, "live 3D view node (Rerun) of one vehicle on the bus"),
}


def parse_tool(argv: Sequence[str]) -> Any:
    """The settings of ``skyloop NAME ARGS`` (``argv`` = [NAME, *ARGS]); ``--help``
    exits 0, a bad command line exits 2 with one line."""
    cls, _, description = COMMANDS[argv[0]]
    return parse(cls, list(argv[1:]), prog=f"skyloop {argv[0]}", description=description)


def run_tool(name: str, argv: Sequence[str]) -> int:
    """``skyloop NAME ARGS``: parse (exit 2 on a bad value), run."""
    return COMMANDS[name][1](parse_tool([name, *argv]))
