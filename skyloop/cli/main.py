"""The ``skyloop`` command: one entry point, one small function per subcommand."""

from __future__ import annotations

import argparse
import signal
import sys

EVAL_HELP = "evaluate a policy: success/collision/timeout rates, 95% CI"


def _cmd_train(args: argparse.Namespace) -> int:
    from skyloop.cli.train import main as train_main

    return train_main(args.rest)


def _cmd_learner(args: argparse.Namespace) -> int:
    from skyloop.cli.learner import main as learner_main

    return learner_main(args.rest)


def _cmd_health(args: argparse.Namespace) -> int:
    from skyloop.health import main as health_main

    return health_main(args.rest)


def _cmd_eval(args: argparse.Namespace) -> int:
    from policy.training.settings import EvalConfig  # light: parsing imports no torch
    from skyloop.cli.dataclass_cli import parse

    c = parse(EvalConfig, args.rest, prog="skyloop eval", description=EVAL_HELP)
    from policy.training.evaluate import evaluate, format_summary

    summary = evaluate(c.policy, c.scenario, c.episodes, c.seed, c.json_path,
                       worlds=c.worlds, validation=c.validation)
    print(format_summary(summary))
    return 0


def _add_group(sub: argparse._SubParsersAction, group: str, text: str) -> None:
    """``skyloop GROUP`` in ``skyloop --help`` and its commands in ``skyloop GROUP
    --help``; each command's options are generated (``skyloop.cli.tools``)."""
    from skyloop.cli.tools import COMMANDS as TOOLS

    p = sub.add_parser(group, help=text)
    gsub = p.add_subparsers(dest=f"{group}_command", required=True)
    for name, (_, _, help_text) in TOOLS.items():
        if name.startswith(group + " "):
            _generated(gsub, name, help_text, word=name.split()[1])


def _generated(sub: argparse._SubParsersAction, name: str, text: str,
               word: str | None = None) -> None:
    """``skyloop NAME`` in ``skyloop --help``; its options are generated from a dataclass
    (``skyloop.cli.tools``), and ``main`` hands it the rest of the command line."""
    p = sub.add_parser(word or name, help=f"{text} (see '{name} --help')", add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=lambda args: _cmd_tool(name, args))


def _cmd_tool(name: str, args: argparse.Namespace) -> int:
    from skyloop.cli.tools import run_tool

    return run_tool(name, args.rest)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="skyloop", description="Software-in-the-loop drone stack (see README.md)."
    )
    from skyloop import __version__

    parser.add_argument("--version", action="version", version=f"skyloop {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    from skyloop.cli.tools import COMMANDS as TOOLS

    for name in ("demo", "render", "bench"):
        _generated(sub, name, TOOLS[name][2])

    _add_group(sub, "log", "episode logs (MCAP): repair")

    p = sub.add_parser("train", help="train TD3/DDPG with a goal reward in the in-process env "
                       "(see 'train --help')", add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("eval", help=EVAL_HELP.replace("%", "%%") + " (see 'eval --help')",
                       add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=_cmd_eval)

    _generated(sub, "plot", TOOLS["plot"][2])

    _add_group(sub, "experiment", "grids of training runs on Ray Tune, and reports")
    from skyloop.cli.stack import add_stack_commands

    add_stack_commands(sub)
    for name in ("record", "router", "certs"):
        _generated(sub, name, TOOLS[name][2])
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
# (skyloop.cli.dataclass_cli): main() hands them the rest of the command line.
GENERATED = {"train": _cmd_train, "eval": _cmd_eval, "learner": _cmd_learner,
             "health": _cmd_health}
STACK = ("sim", "perception", "policy", "bridge", "up")  # skyloop.cli.stack.COMMANDS
#: commands that install their own SIGINT/SIGTERM handling before they open anything;
#: until then a signal ends them at once (skyloop.signals.exit_at_once). The others get
#: Python's own handling back before they run.
OWN_SIGNALS = (*STACK, "record", "router", "learner", "viz", "view")
#: nodes that have closed everything (bus, links, files) when their command returns, and
#: start no thread that must finish and no exit handler of their own: their process
#: ends then, without the interpreter's finalization (tearing down torch, numba and
#: JSBSim took 0.6-1 s of the 2 s a node has to stop in: the policy exited 1.3-1.6 s
#: after a signal mid-episode, 0.01-0.06 s without).
QUICK_EXIT = ("sim", "perception", "policy", "bridge")


def _tool(argv: list[str]) -> tuple[str, list[str]] | None:
    """``(name, rest)`` of a command of ``skyloop.cli.tools`` (``demo``, ``experiment
    run``, ...)."""
    from skyloop.cli.tools import command_of

    return command_of(argv)


def main(argv: list[str] | None = None) -> int:
    """``skyloop ARGS``: the exit code. A closed standard output (``skyloop train --help
    | head -3``) ends it quietly, 141 (``skyloop.signals.quiet_broken_pipe``). Run as the
    ``skyloop`` command, a node of :data:`QUICK_EXIT` ends here without the
    interpreter's finalization (``skyloop.signals.quick_exit``)."""
    from skyloop.signals import quick_exit, quiet_broken_pipe, started_as_command

    args = sys.argv[1:] if argv is None else list(argv)
    code = quiet_broken_pipe(lambda: _main(args))
    if argv is None and args and args[0] in QUICK_EXIT and started_as_command():
        quick_exit(code)
    return code


def _main(argv: list[str]) -> int:
    if not argv or argv[0] not in OWN_SIGNALS:
        from skyloop.signals import default_signals

        default_signals()
    if argv and argv[0] in GENERATED:  # their parsers are generated from dataclasses (tyro)
        args = argparse.Namespace(command=argv[0], rest=argv[1:], func=GENERATED[argv[0]])
    elif argv and argv[0] in STACK:  # generated too (skyloop.cli.stack_settings)
        from skyloop.cli.stack import run_node

        args = argparse.Namespace(command=argv[0], rest=argv[1:],
                                  func=lambda a: run_node(a.command, a.rest))
    elif (found := _tool(argv)) is not None:  # and these (skyloop.cli.tools)
        args = argparse.Namespace(command=found[0], rest=found[1],
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
