"""``skyloop demo``: fly the shipped policy through a scenario in the in-process env.

It prints one line per episode and a summary, flies the scripted straight-line
controller (:mod:`policy.algorithms.scripted`) on the same seeds for comparison, and writes a
picture of every episode's path. (The full process graph over Zenoh and MAVLink
replaces the in-process env here once ``skyloop up`` lands.)
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from policy.algorithms.scripted import StraightLineController
from policy.training.evaluate import env_for, make_controller
from policy.training.rollout import run_episodes, summarize


def run_demo(scenario: str, episodes: int, seed: int, out_dir: Path,
             policy: str | None = None) -> dict:
    from sitl.render.scene import render_scene

    controller = make_controller(policy, task=None)
    print(f"skyloop demo: {episodes} episodes of '{scenario}' flown by the "
          f"{controller.name}, in-process env, seeds {seed}..{seed + episodes - 1}")
    env = env_for(controller, scenario)  # the state it was trained to read
    results, steps, t0 = [], 0, time.perf_counter()
    for r in run_episodes(env, controller, episodes, seed):
        results.append(r)
        steps += r.steps
        print(f"  episode {len(results):3d}  seed {r.seed:6d}  {r.outcome:9s}  "
              f"steps {r.steps:3d}  return {r.episode_return:8.1f}  path {r.path_length:6.1f} m")
    wall = time.perf_counter() - t0
    summary = summarize(results)
    summary["env_steps_per_s"] = steps / wall if wall > 0 else 0.0
    lo, hi = summary["success_ci95"]
    print(f"summary: success {summary['success_rate']:.0%} (95% CI {lo:.0%}-{hi:.0%}), "
          f"collision {summary['collision_rate']:.0%}, timeout {summary['timeout_rate']:.0%}, "
          f"mean steps {summary['mean_steps']:.0f}, {summary['env_steps_per_s']:.0f} env steps/s")
    if not isinstance(controller, StraightLineController):
        base = summarize(list(run_episodes(env, StraightLineController(), episodes, seed)))
        summary["scripted_success_rate"] = base["success_rate"]
        print(f"same seeds, scripted straight-line controller: success "
              f"{base['success_rate']:.0%}, collision {base['collision_rate']:.0%}")
    out_dir.mkdir(parents=True, exist_ok=True)
    png = out_dir / f"demo_{scenario}.png"
    render_scene(env.world, start=np.array([r.start for r in results]),
                 goal=np.array([r.goal for r in results]),
                 paths=[r.path for r in results], out=png,
                 title=f"{scenario}: {episodes} episodes, {controller.name}")
    print(f"paths of every episode: {png}")
    env.close()
    summary["png"] = str(png)
    summary["controller"] = controller.name
    summary["path_endpoints"] = [np.asarray(r.path[-1]).tolist() for r in results]
    return summary
