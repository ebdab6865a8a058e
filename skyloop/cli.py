"""The ``skyloop`` command (placeholder until subcommands land)."""

from __future__ import annotations

import argparse


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="skyloop")
    parser.parse_args(argv)
    return 0
