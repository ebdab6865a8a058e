"""Log in-process env episodes in the stack's episode-log format (``bus.log.writer``).

The same topics and contract as a stack run (see :mod:`policy.logs.offline`): episode
START/END, one observation, one truth pose per step, one ``cmd_vel`` per action and the
env's step record (``step_record``) after each step, so ``skyloop train --from-logs``
learns from in-process runs and stack runs alike.
Times are sim times (0.1 s a step) so the file is byte-identical for the same seed.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from bus import messages as m
from bus.keys import CMD_VEL, EPISODE, OBSERVATION, STEP_RECORD, TRUTH
from bus.log.writer import EpisodeLogWriter
from bus.task import TASK, episode_outcome
from perception.observation import scaling_fields
from policy.training.rollout import Controller

NS = 1_000_000_000


def log_env_episodes(env, controller: Controller, episodes: int, seed: int, out_dir: Path,
                     vehicle: str = "uav1", run_name: str = "env",
                     split_episodes: int = 0) -> Path:
    """Fly ``episodes`` episodes (seeds ``seed + i``) and write them to an MCAP log (a
    new file every ``split_episodes``); returns the (first) file."""
    base = env.unwrapped
    writer = EpisodeLogWriter(out_dir, run_name=run_name, split_episodes=split_episodes)
    clock = 0  # ns, monotonic across episodes
    scaling = scaling_fields(base.obs_config)

    def put(topic: str, msg, t_s: float) -> None:
        writer.write_msg(vehicle, topic, msg, log_time_ns=clock + int(round(t_s * NS)))

    for i in range(episodes):
        state, info = env.reset(seed=seed + i)
        scenario = base.config.episode.scenario
        put(EPISODE, m.episode_start(i, seed + i, base.start, base.goal, 0.0, scenario,
                                     base.task), 0.0)
        k, t = 0, 0.0

        def snapshot(episode: int, step: int, t_s: float, latest: np.ndarray) -> None:
            truth = base.vehicle.truth
            put(OBSERVATION, m.observation(latest, t_s, episode=episode, step=step,
                                           scaling=scaling), t_s)
            put(TRUTH, m.odometry(truth.position, truth.velocity, (0.0, 0.0, 0.0, 1.0), t_s),
                t_s)

        snapshot(i, 0, 0.0, state[-1])
        while True:
            action = np.clip(np.asarray(controller(state), np.float32), -TASK.max_action,
                             TASK.max_action)
            put(CMD_VEL, m.velocity_setpoint(action[:3], float(action[3]), t, body=True), t)
            state, _, terminated, truncated, info = env.step(action)
            k, t = k + 1, t + 0.1
            put(STEP_RECORD, m.step_record(replace(base.record, episode=i), t), t)
            snapshot(i, k, t, state[-1])
            if terminated or truncated:
                break
        outcome = episode_outcome(info["goal_reached"], info["collision"])
        put(EPISODE, m.episode_end(i, outcome, k, t, seed=seed + i, scenario=scenario), t)
        clock += int(round((t + 1.0) * NS))
    writer.close()
    return writer.paths[0]
