"""The ``skyloop`` command: one entry point, one small function per subcommand."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _cmd_demo(args: argparse.Namespace) -> int:
    from skyloop.demo import run_demo

    summary = run_demo(args.scenario, args.episodes, args.seed, Path(args.out_dir))
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2))
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from skyloop.render import render_scenario

    path = render_scenario(args.scenario, args.seed, Path(args.out))
    print(f"wrote {path}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from skyloop.bench import run_bench

    run_bench(quick=args.quick, json_path=Path(args.json) if args.json else None,
              only=args.only)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="skyloop", description="Software-in-the-loop drone stack (see README.md)."
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("demo", help="fly a controller through a scenario, print a summary")
    p.add_argument("--scenario", default="valley")
    p.add_argument("--episodes", type=int, default=5)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--out-dir", default="out")
    p.add_argument("--json", help="write the summary as JSON here")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("render", help="draw a scenario: terrain, start/goal, a scan, faces")
    p.add_argument("--scenario", default="valley")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="out/scenario.png")
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser("bench", help="measure speed against peers; prints a table, writes JSON")
    p.add_argument("--quick", action="store_true", help="a short run (under 45 s)")
    p.add_argument("--json", help="write the results as JSON here")
    p.add_argument("--only", nargs="*", help="run only these benchmark modules")
    p.set_defaults(func=_cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError) as exc:  # bad input: a clear message, no traceback
        print(f"skyloop {args.command}: error: {exc}", file=sys.stderr)
        return 2
