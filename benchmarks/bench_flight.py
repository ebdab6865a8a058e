"""Flight benchmark: JSBSim F450 physics alone, and the whole simulated vehicle.

Keys (medians of several repeats, one core):

- ``fdm_steps_per_s``: JSBSim physics steps per second at dt = 1/500 s for the model
  skyloop flies (JSBSim's F450 files + ``sitl/fcs/f450_attitude_rate.xml``), hovering
  with the inner loops engaged.  ``fdm_control_steps_per_s`` is the same / 50, the
  ceiling for a 0.1 s control step.
- ``flight_model_steps_per_s``: control steps per second of ``Vehicle.step`` (50 physics
  steps + 5 outer ticks of IMU, estimator propagation and autopilot + one Kalman
  predict/update with GPS, baro and magnetometer) under random setpoints.
- ``controller_estimator_ms_per_step``: the Python share of one control step (the
  difference of the two above); DESIGN.md budgets 0.3 ms for it.
- ``flight_model_steps_per_s_outer_<hz>hz`` (full run only): the same at other
  outer-loop rates.

``peers``: ``jsbsim_stock_f450_steps_per_s``, JSBSim's stock F450 (its own
FlightControl.xml and Sensor*.xml systems, rate loop engaged), measured side by side.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import time

import jsbsim
import numpy as np

from sitl.flight_model import FlightModel
from sitl.vehicle import Vehicle, VehicleConfig


def _rate(fn, count: int, repeats: int) -> float:
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        rates.append(count / (time.perf_counter() - t0))
    return statistics.median(rates)


def measure_fdm(steps: int, repeats: int) -> float:
    fm = FlightModel()
    fm.reset(0.0, 0.0, 50.0, 0.0)
    return _rate(lambda: fm.run(steps), steps, repeats)


def measure_stock_f450(steps: int, repeats: int) -> float:
    """JSBSim's own F450 as shipped; its load-time chatter goes to /dev/null."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    os.dup2(null, 2)
    try:
        fdm = jsbsim.FGFDMExec(jsbsim.get_default_root_dir())
        fdm.set_debug_level(0)
        fdm.load_model("F450")
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, null):
            os.close(fd)
    fdm.set_dt(1.0 / 500.0)
    fdm["ic/h-agl-ft"] = 50.0 / 0.3048
    fdm.run_ic()
    fdm["propulsion/set-running"] = -1
    fdm["fcs/ScasEngage"] = 1.0
    fdm["fcs/throttle-cmd-norm"] = 0.4068
    run = fdm.run

    def go() -> None:
        for _ in range(steps):
            run()

    return _rate(go, steps, repeats)


def measure_vehicle(steps: int, repeats: int, outer_hz: float = 50.0) -> float:
    v = Vehicle(VehicleConfig(outer_hz=outer_hz), seed=0)
    rng = np.random.default_rng(0)
    setpoints = rng.uniform(-2.0, 2.0, (steps, 4)) * [1.0, 1.0, 0.2, 1.0]
    rep = iter(range(10**6))

    def go() -> None:
        v.reset(np.array([0.0, 0.0, 30.0]), 0.0, seed=next(rep))
        for sp in setpoints:
            v.step(sp)

    return _rate(go, steps, repeats)


def run(quick: bool) -> dict:
    fdm_steps, steps, repeats = (10_000, 300, 3) if quick else (50_000, 1_000, 7)
    result: dict = {"fdm_steps_per_s": measure_fdm(fdm_steps, repeats)}
    result["fdm_control_steps_per_s"] = result["fdm_steps_per_s"] / 50.0
    result["flight_model_steps_per_s"] = measure_vehicle(steps, repeats)
    result["controller_estimator_ms_per_step"] = 1e3 * (
        1.0 / result["flight_model_steps_per_s"] - 1.0 / result["fdm_control_steps_per_s"])
    if not quick:
        for hz in (10.0, 20.0, 100.0):
            result[f"flight_model_steps_per_s_outer_{hz:.0f}hz"] = measure_vehicle(
                steps, repeats, hz)
    result["peers"] = {"jsbsim_stock_f450_steps_per_s": measure_stock_f450(fdm_steps, repeats)}
    return result


def main(argv: list[str]) -> int:
    res = run("--quick" in argv)
    peers = res.pop("peers")
    width = max(map(len, [*res, *peers]))
    for key, val in res.items():
        print(f"{key:<{width}}  {val:12,.3f}")
    for key, val in peers.items():
        print(f"{key:<{width}}  {val:12,.3f}  (peer)")
    if "--json" in argv:
        with open(argv[argv.index("--json") + 1], "w") as fh:
            json.dump({**res, "peers": peers}, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
