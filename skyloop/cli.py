"""The ``skyloop`` command: one entry point, one small function per subcommand."""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from skyloop.argtypes import nonnegative_int

EVAL_HELP = "evaluate a policy: success/collision/timeout rates, 95% CI"


def _cmd_train(args: argparse.Namespace) -> int:
    from skyloop.train_cli import main as train_main

    return train_main(args.rest)


def _cmd_learner(args: argparse.Namespace) -> int:
    from skyloop.learner_cli import main as learner_main

    return learner_main(args.rest)


def _cmd_health(args: argparse.Namespace) -> int:
    from skyloop.health import main as health_main

    return health_main(args.rest)


def _cmd_log_repair(args: argparse.Namespace) -> int:
    from bus.log import recover_log

    src = Path(args.path)
    if not src.exists():
        raise FileNotFoundError(f"{src}: no such log file or run directory")
    out, report = recover_log(src, args.out)
    print(f"repaired: {out} ({report.summary()})")
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from policy.evaluate import EvalConfig, evaluate, format_summary
    from skyloop.dataclass_cli import parse

    c = parse(EvalConfig, args.rest, prog="skyloop eval", description=EVAL_HELP)
    summary = evaluate(c.policy, c.scenario, c.episodes, c.seed, c.json_path,
                       worlds=c.worlds, validation=c.validation)
    print(format_summary(summary))
    return 0


def _cmd_plot(args: argparse.Namespace) -> int:
    from policy.plots import plot_runs

    out = plot_runs([Path(d) for d in args.runs], Path(args.out))
    print(f"wrote {out}")
    return 0


def _cmd_experiment_run(args: argparse.Namespace) -> int:
    from skyloop.experiment.grid import load_grid
    from skyloop.experiment.run import run_grid

    grid = load_grid(args.grid)  # every error before anything starts
    status = run_grid(grid, Path(args.out), max_concurrent=args.max_concurrent,
                      address=args.address, cpus_per_trial=args.cpus_per_trial)
    return 0 if all(s == "finished" for s in status.values()) else 1


def _cmd_experiment_report(args: argparse.Namespace) -> int:
    from skyloop.experiment.report import write_report

    paths = write_report(Path(args.dir), eval_episodes=args.eval_episodes)
    for path in paths:
        print(f"wrote {path}")
    return 0


def _add_experiment(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("experiment", help="grids of training runs on Ray Tune, and reports")
    esub = p.add_subparsers(dest="experiment_command", required=True)
    r = esub.add_parser("run", help="run or continue a grid (finished trials are skipped)")
    r.add_argument("grid", help="grid file (TOML), e.g. experiments/paper_static.toml")
    r.add_argument("--out", required=True, help="grid directory: one run directory per trial")
    r.add_argument("--max-concurrent", type=int, metavar="N",
                   help="at most N trials at once (default: the cluster's CPUs per trial)")
    r.add_argument("--address", help="an existing Ray cluster (default: $RAY_ADDRESS, or "
                   "an embedded Ray on this machine)")
    r.add_argument("--cpus-per-trial", type=int, metavar="N",
                   help="CPUs Ray reserves for each trial (default: 1 for sync trials, "
                   "2 for parallel ones: learner and collector)")
    r.set_defaults(func=_cmd_experiment_run)
    r = esub.add_parser("report", help="REPORT.md, summary.json and figures of a grid")
    r.add_argument("dir", help="grid directory written by 'skyloop experiment run'")
    r.add_argument("--eval-episodes", type=nonnegative_int, default=0, metavar="N",
                   help="evaluate each final actor on N held-out episodes (default: 0)")
    r.set_defaults(func=_cmd_experiment_report)


def _generated(sub: argparse._SubParsersAction, name: str, text: str) -> None:
    """``skyloop NAME`` in ``skyloop --help``; its options are generated from a dataclass
    (``skyloop.tool_cli``), and ``main`` hands it the rest of the command line."""
    p = sub.add_parser(name, help=f"{text} (see '{name} --help')", add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=lambda args: _cmd_tool(name, args))


def _cmd_tool(name: str, args: argparse.Namespace) -> int:
    from skyloop.tool_cli import run_tool

    return run_tool(name, args.rest)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="skyloop", description="Software-in-the-loop drone stack (see README.md)."
    )
    from skyloop import __version__

    parser.add_argument("--version", action="version", version=f"skyloop {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    from skyloop.tool_cli import COMMANDS as TOOLS

    for name in ("demo", "render", "bench"):
        _generated(sub, name, TOOLS[name][2])

    p = sub.add_parser("log", help="episode logs (MCAP): repair")
    log_sub = p.add_subparsers(dest="log_command", required=True)
    r = log_sub.add_parser("repair", help="write an indexed, finished copy of a log whose "
                                          "writer died (SIGKILL, power loss)")
    r.add_argument("path", help="the .mcap file or its run directory")
    r.add_argument("--out", default=None, metavar="DIR",
                   help="where the copy's run directory goes (default: beside the source "
                        "run, named <run>-recovered)")
    r.set_defaults(func=_cmd_log_repair)

    p = sub.add_parser("train", help="train TD3/DDPG with a goal reward in the in-process env "
                       "(see 'train --help')", add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("eval", help=EVAL_HELP.replace("%", "%%") + " (see 'eval --help')",
                       add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=_cmd_eval)

    p = sub.add_parser("plot", help="success/collision curves of one or more training runs")
    p.add_argument("runs", nargs="+", help="run directories")
    p.add_argument("--out", default="out/curves.png")
    p.set_defaults(func=_cmd_plot)

    _add_experiment(sub)
    from skyloop.stack_cli import add_stack_commands

    add_stack_commands(sub)
    p = sub.add_parser("learner", help="learn from live episodes on the bus, publish actor "
                       "weights that 'policy --weights-from-bus' nodes fly (see 'learner "
                       "--help')", add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=_cmd_learner)
    for name in ("view", "viz"):
        _generated(sub, name, TOOLS[name][2])
    p = sub.add_parser("health", help="is this node up: router reachable, session connected, "
                       "ports bound, readiness token, topic published (a container health "
                       "check; exit 0 or 1; see 'health --help')", add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=_cmd_health)
    return parser


# Subcommands whose options are generated from config dataclasses with tyro
# (skyloop.dataclass_cli): main() hands them the rest of the command line.
GENERATED = {"train": _cmd_train, "eval": _cmd_eval, "learner": _cmd_learner,
             "health": _cmd_health}
STACK = ("sim", "perception", "policy", "bridge", "up")  # skyloop.stack_cli.COMMANDS
TOOLS = ("demo", "render", "bench", "view", "viz")  # skyloop.tool_cli.COMMANDS


def main(argv: list[str] | None = None) -> int:
    """``skyloop ARGS``: the exit code. A closed standard output (``skyloop train --help
    | head -3``) ends it quietly, 141 (``skyloop.signals.quiet_broken_pipe``)."""
    from skyloop.signals import quiet_broken_pipe

    return quiet_broken_pipe(lambda: _main(sys.argv[1:] if argv is None else list(argv)))


def _main(argv: list[str]) -> int:
    if argv and argv[0] in ("record", "router", "certs"):  # their own parsers take every flag
        from skyloop.stack_cli import passthrough

        return passthrough(argv[0], argv[1:])
    if argv and argv[0] in GENERATED:  # their parsers are generated from dataclasses (tyro)
        args = argparse.Namespace(command=argv[0], rest=argv[1:], func=GENERATED[argv[0]])
    elif argv and argv[0] in STACK:  # generated too (skyloop.stack_settings)
        from skyloop.stack_cli import run_node

        args = argparse.Namespace(command=argv[0], rest=argv[1:],
                                  func=lambda a: run_node(a.command, a.rest))
    elif argv and argv[0] in TOOLS:  # and these (skyloop.tool_cli)
        args = argparse.Namespace(command=argv[0], rest=argv[1:],
                                  func=lambda a: _cmd_tool(a.command, a))
    else:
        args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM as skyloop.signals.Stopped
        signum = getattr(exc, "signum", signal.SIGINT)
        print("terminated" if signum == signal.SIGTERM else "interrupted", file=sys.stderr)
        return 128 + signum
    except (ValueError, FileNotFoundError, FileExistsError) as exc:  # bad input: no traceback
        print(f"skyloop {args.command}: error: {exc}", file=sys.stderr)
        return 2
