"""Flight benchmark: JSBSim F450 physics alone, and the whole simulated vehicle.

Keys (medians of several repeats, one core):

- ``fdm_steps_per_s``: JSBSim physics steps per second at dt = 1/500 s for the model
  skyloop flies (JSBSim's F450 files + ``sitl/flight/fcs/f450_attitude_rate.xml``), hovering
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

from sitl.flight.flight_model import FlightModel
from sitl.flight.vehicle import Vehicle, VehicleConfig


def _timed(fn, count: int) -> float:
    t0 = time.perf_counter()
    fn()
    return count / (time.perf_counter() - t0)


def _stock_f450() -> jsbsim.FGFDMExec:
    """JSBSim's own F450 as shipped, hovering; its load-time chatter goes to /dev/null."""
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
    return fdm


def _physics(fdm_run, steps: int):
    def go() -> None:
        for _ in range(steps):
            fdm_run()
    return go


def _flight(v: Vehicle, setpoints: np.ndarray):
    seeds = iter(range(10**6))

    def go() -> None:
        v.reset(np.array([0.0, 0.0, 30.0]), 0.0, seed=next(seeds))
        for sp in setpoints:
            v.step(sp)
    return go


def run(quick: bool) -> dict:
    """All measurements interleaved round-robin, so machine load hits them alike."""
    fdm_steps, steps, repeats = (10_000, 300, 3) if quick else (50_000, 1_000, 7)
    fm = FlightModel()
    fm.reset(0.0, 0.0, 50.0, 0.0)
    stock = _stock_f450()
    setpoints = np.random.default_rng(0).uniform(-2.0, 2.0, (steps, 4)) * [1.0, 1.0, 0.2, 1.0]
    outer_rates = (50.0,) if quick else (50.0, 10.0, 20.0, 100.0)
    jobs = {"fdm_steps_per_s": (_physics(fm.fdm.run, fdm_steps), fdm_steps),
            "jsbsim_stock_f450_steps_per_s": (_physics(stock.run, fdm_steps), fdm_steps)}
    for hz in outer_rates:
        key = ("flight_model_steps_per_s" if hz == 50.0
               else f"flight_model_steps_per_s_outer_{hz:.0f}hz")
        jobs[key] = (_flight(Vehicle(VehicleConfig(outer_hz=hz), seed=0), setpoints), steps)
    rates: dict[str, list[float]] = {key: [] for key in jobs}
    for _ in range(repeats):
        for key, (fn, count) in jobs.items():
            rates[key].append(_timed(fn, count))
    med = {key: statistics.median(r) for key, r in rates.items()}
    result: dict = {"fdm_steps_per_s": med.pop("fdm_steps_per_s")}
    result["fdm_control_steps_per_s"] = result["fdm_steps_per_s"] / 50.0
    result["flight_model_steps_per_s"] = med.pop("flight_model_steps_per_s")
    result["controller_estimator_ms_per_step"] = 1e3 * (
        1.0 / result["flight_model_steps_per_s"] - 1.0 / result["fdm_control_steps_per_s"])
    result["peers"] = {"jsbsim_stock_f450_steps_per_s": med.pop("jsbsim_stock_f450_steps_per_s")}
    result.update(med)
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
