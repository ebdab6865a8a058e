"""Benchmarks: each module exposes run(quick) -> dict of measured numbers."""
