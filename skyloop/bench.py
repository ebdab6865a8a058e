"""``skyloop bench``: run every benchmark module, print a table, write JSON.

Each ``benchmarks/bench_<area>.py`` exposes ``run(quick) -> dict`` with medians of
several repeats and its peers (measured side by side in the same run) under "peers".
The report names the machine and the command so that anyone can reproduce it.
"""

from __future__ import annotations

import importlib
import json
import os
import platform
import sys
import time
from pathlib import Path

MODULES = ["bench_flight", "bench_lidar", "bench_perception", "bench_env", "bench_td3",
           "bench_train", "bench_stack", "bench_viz", "bench_record", "bench_mavlink_fuzz",
           "bench_soak"]
#: run only when named in ``--only`` (an hour by default)
ON_REQUEST = {"bench_soak"}


def machine() -> dict:
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "platform": platform.platform()}


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:,.3f}" if value < 10 else f"{value:,.0f}"
    return str(value)


def run_bench(quick: bool, json_path: Path | None, only: list[str] | None = None,
              minutes: float | None = None) -> dict:
    # One core: the goals are stated per core, and peers get the same.
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")
    report: dict = {"machine": machine(), "command": " ".join(["skyloop", *sys.argv[1:]]),
                    "quick": quick, "results": {}, "peers": {}}
    print(f"machine: {report['machine']['cpu']} ({report['machine']['cores']} cores), "
          f"python {report['machine']['python']}")
    print(f"command: {report['command']}  (each number: median of several repeats)")
    t_start = time.perf_counter()
    for name in MODULES:
        named = bool(only) and (name in only or name.removeprefix("bench_") in only)
        if (only and not named) or (name in ON_REQUEST and not named):
            continue
        try:
            module = importlib.import_module(f"benchmarks.{name}")
        except ImportError as exc:
            print(f"  {name}: skipped ({exc})")
            continue
        t0 = time.perf_counter()
        numbers = module.run(quick, minutes) if name == "bench_soak" else module.run(quick)
        report["peers"].update(numbers.pop("peers", {}))
        report["results"].update(numbers)
        print(f"  {name} done in {time.perf_counter() - t0:.1f} s")
    report["wall_s"] = time.perf_counter() - t_start
    width = max((len(k) for k in [*report["results"], *report["peers"]]), default=10)
    print(f"\n{'metric':<{width}}  value")
    for key, value in report["results"].items():
        print(f"{key:<{width}}  {_fmt(value)}")
    for key, value in report["peers"].items():
        print(f"{key:<{width}}  {_fmt(value)}  (peer)")
    print(f"total {report['wall_s']:.1f} s")
    flat = {**report["results"], "peers": report["peers"], "machine": report["machine"],
            "command": report["command"], "quick": quick}
    if json_path:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(flat, indent=2))
        print(f"wrote {json_path}")
    return flat
