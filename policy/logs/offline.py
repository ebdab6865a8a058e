"""Learning from logged episodes: ``skyloop train --from-logs PATH...``.

An episode log (``bus.log.writer``, MCAP with ROS 2 schemas) holds, per vehicle and episode,
the messages this module rebuilds transitions from (the *log contract*):

- ``episode`` START (seed, start, goal, the episode limits it runs under) and END
  (outcome, steps T); training takes the first usable episode's limits as its task
  (recorded in the actor file) and refuses, counted, episodes run under other goal limits;
- ``observation``: one 35-attribute observation per step, ``step`` = 0 .. T, each with
  the scaling it was made with (``Observation.msg``; an episode whose observations do
  not record it, or record two, is refused and counted);
- ``cmd_vel`` (``VelocitySetpoint``) in the body frame with a yaw rate: the policy's
  action of each step 0 .. T-1, body-horizontal (forward, left, up, yaw_rate), as the
  env and the stack apply it (world-frame or heading setpoints are not policy actions);
- ``truth``: the true pose per step 0 .. T (for the distance and altitude terms);
- ``step_record`` (``StepRecord``, logs made since it exists): the simulator's record of
  each step 1 .. T (D_pre, D_cur, altitude, h, g, collision, outcome), joined by its own
  (episode, step) fields.

Stack logs end an episode without a scan after the last step; its observation (the last
next state) is then approximated by :func:`terminal_observation`. Rewards are eq. 3.5 of
each step's record where the log has records, else recomputed from the truth distances
and altitude and the logged h, g un-scaled with the recorded scaling; the two are
checked against each other where both exist (:mod:`policy.logs.transitions`); then
TR/NGR/EGR/ABR rewrite the episode as in online training, so one log serves every goal
reward. States are the 3-frame stacks, zero-padded at the start.

Offline data has no exploration of the learner's own: ``--bc`` trains TD3+BC
(Fujimoto & Gu 2021, eq. 3: pi = argmax E[lambda Q(s, pi(s)) - (pi(s) - a)^2],
lambda = alpha / mean|Q|, alpha = 2.5) instead of plain TD3.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from bus import keys
from bus.log.reader import EpisodeLogReader, log_files
from bus.log.writer import read_episodes
from bus.messages import (
    episode_limits,
    is_action,
    nanoseconds,
    observation_scaling,
    observation_values,
    odometry_values,
    setpoint_values,
    step_record_values,
)
from bus.task import TASK, TaskSpec
from policy.algorithms.agents import make_goal_reward
from policy.algorithms.replay import ReplayBuffer
from policy.algorithms.rewards import RewardConfig
from policy.algorithms.td3 import TD3, TD3Config, flush_denormals
from policy.logs.transitions import (  # noqa: F401 - Transitions, terminal_observation re-exported
    FRAMES,
    OBS_DIM,
    EpisodeSteps,
    Transitions,
    add_episode,
    terminal_observation,
    transitions_from_steps,
)
from policy.training.settings import OFFLINE_UPDATES


@dataclass
class LogReport:
    episodes_used: int = 0
    transitions: int = 0
    skipped: dict[str, int] = field(default_factory=dict)  # reason -> count
    files: list[str] = field(default_factory=list)
    task: TaskSpec | None = None  # what the episodes used were run under

    def skip(self, reason: str) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1


def episode_steps(episode, commands: dict[int, tuple] | None = None,
                  observations: dict[tuple[Any, int, int], Any] | None = None) -> EpisodeSteps:
    """Decode a logged episode (``bus.log.reader.Episode``) into :class:`EpisodeSteps`.

    ``commands`` (body-frame ``cmd_vel`` of the whole file by stamp) recovers an action
    the recorder saw after the episode's END event: in a stack run commands come from
    the bridge and events from the sim, so the last command can arrive late (and the
    previous episode's last one inside this episode's range, which the stamps leave out).
    Observations are joined by their own (episode, step) fields, never by where they
    lie in the log: perception's observation of the next episode's step 0 can reach the
    recorder before the sim's START does (two paths through the bus), and so lie inside
    this episode's range. ``observations`` (every observation of the file by (episode,
    step) per vehicle, :func:`file_observations`) also finds such an observation for its
    own episode.
    """
    T = episode.steps
    if T is None or T < 1:
        raise ValueError("no steps")
    start = episode.start_event
    goal = np.array([start.goal.x, start.goal.y, start.goal.z])
    if observations is None:
        observations = {(episode.vehicle, int(o.episode), int(o.step)): o
                        for o in (m.decode() for m in episode.topic("observation"))}
    obs_msgs = [o for (v, e, _), o in observations.items()
                if v == episode.vehicle and e == episode.index]
    obs = {int(o.step): observation_values(o)[-1] for o in obs_msgs}
    truth_msgs = [m.decode() for m in episode.topic("truth")]
    cmds = [c for c in (msg.decode() for msg in episode.topic("cmd_vel")) if is_action(c)]
    actions = [setpoint_values(c) for c in cmds]
    if len(actions) != T:
        # a command in this episode's range that answers another episode's step (the
        # previous episode's last, arriving late), or this episode's last arriving after
        # END: take the command of each of this episode's steps by its stamp, the step it
        # answers (the window's own first, then the file's)
        by_stamp = {**(commands or {}),
                    **{nanoseconds(c.header.stamp): setpoint_values(c) for c in cmds}}
        stamps = [nanoseconds(t.header.stamp) for t in truth_msgs]
        actions = [by_stamp[t] for t in stamps[:T] if t in by_stamp]
    records = [step_record_values(r.decode()) for r in episode.topic(keys.STEP_RECORD)]
    return EpisodeSteps(goal, T, episode.outcome, obs,
                        [odometry_values(t) for t in truth_msgs], actions,
                        [observation_scaling(o) for o in obs_msgs], episode_limits(start),
                        {r.step: r for r in records if r.episode == episode.index} or None)


def rebuild_episode(episode, config: RewardConfig,
                    commands: dict[int, tuple] | None = None,
                    observations: dict[tuple[Any, int, int], Any] | None = None
                    ) -> Transitions:
    """Transitions of one complete logged episode; ``ValueError`` names what does not
    fit (:func:`episode_steps`, then :func:`policy.logs.transitions.transitions_from_steps`)."""
    return transitions_from_steps(episode_steps(episode, commands, observations), config)


def task_of(limits: dict[str, float] | None) -> TaskSpec | None:
    """The task a log's episode was run under: ``TASK`` with its recorded episode limits
    (None when it records none)."""
    if limits is None:
        return None
    steps = limits["max_steps"]
    return replace(TASK, max_steps=TASK.max_steps if math.isinf(steps) else int(steps),
                   goal_radius=limits["goal_radius"],
                   goal_max_altitude=limits["goal_max_altitude"])


def file_observations(path: Path) -> dict[tuple[Any, int, int], Any]:
    """Every decodable ``observation`` of a log by (vehicle, episode, step)."""
    out = {}
    for msg in EpisodeLogReader(path).messages():
        if msg.name == "observation":
            try:
                o = msg.decode()
            except Exception:  # counted by the reader's report
                continue
            out[(msg.vehicle, int(o.episode), int(o.step))] = o
    return out


def body_commands(path: Path) -> dict[int, tuple]:
    """Every ``cmd_vel`` of a log that is a policy action (body frame, yaw rate) by
    header stamp (ns)."""
    out = {}
    for msg in EpisodeLogReader(path).messages():
        if msg.name == "cmd_vel":
            try:
                cmd = msg.decode()
            except Exception:  # counted by the reader's report; not an action we can use
                continue
            if is_action(cmd):
                out[nanoseconds(cmd.header.stamp)] = setpoint_values(cmd)
    return out


def load_logs(paths: list[Path], buffer: ReplayBuffer, goal_reward,
              config: RewardConfig) -> LogReport:
    """Fill ``buffer`` with every complete episode of ``paths`` (MCAP files, or run
    directories: their ``*.mcap`` files in order, e.g. a log split every N episodes);
    count what is skipped. The episodes train under the task the first usable episode
    records (``report.task``); an episode run under other goal limits is skipped, counted
    with its reason."""
    report = LogReport()
    files = [f for p in map(Path, paths) for f in (log_files(p) if p.is_dir() else [p])]
    for path in files:
        report.files.append(str(path))
        try:
            episodes, read = read_episodes(path, include_incomplete=True)
        except Exception as exc:  # a missing or unreadable file is reported, not fatal
            report.skip(f"unreadable log ({type(exc).__name__}: {exc})")
            continue
        if not episodes:  # nothing usable in it (not an MCAP file, say): named with its path
            report.skip(f"{path}: " + ("; ".join(read.errors[:3]) or "no episodes"))
        for _ in range(read.corrupt_chunks):
            report.skip("corrupt chunk")
        for _ in range(read.corrupt_records):
            report.skip("corrupt record")
        if read.truncated or (read.skipped_bytes and not read.corrupt_chunks):
            report.skip(f"damaged or truncated log ({read.skipped_bytes} bytes unreadable)")
        commands, observations = body_commands(path), file_observations(path)
        for ep in episodes:
            if not ep.complete:
                report.skip(f"incomplete: {ep.problem}")
                continue
            try:
                steps = episode_steps(ep, commands, observations)
                if report.task is None:  # the first episode's task is the run's
                    report.task = task_of(steps.limits)
                tr = transitions_from_steps(steps, config, report.task or TASK)
            except (ValueError, AttributeError) as exc:
                report.skip(f"inconsistent: {exc}")
                continue
            add_episode(tr, buffer, goal_reward)
            report.episodes_used += 1
            report.transitions += len(tr.actions)
    return report


class TD3BC(TD3):
    """TD3+BC (Fujimoto & Gu 2021): TD3 whose actor also imitates the logged actions."""

    alpha = 2.5

    def update(self, batch):
        self._bc_action = batch.action
        return super().update(batch)

    def _actor_loss(self, state: torch.Tensor) -> torch.Tensor:
        pi = self.actor(state)
        q = self.critic.q1(state, pi, detach_params=True)
        lam = self.alpha / q.abs().mean().detach()  # lambda = alpha / mean|Q|
        return -lam * q.mean() + (pi - self._bc_action).pow(2).mean()


UPDATES = OFFLINE_UPDATES  # TD3 updates from the logs (``skyloop train --from-logs --updates``)


def train_from_logs(paths: list[Path], out: Path, reward: str = "abr", updates: int = UPDATES,
                    seed: int = 0, bc: bool = False, init_actor: Path | None = None) -> dict:
    """Rebuild transitions from logs, train TD3 (or TD3+BC), write ``out/actor.pt``."""
    torch.set_num_threads(1)
    config = RewardConfig()
    buffer = ReplayBuffer(1_000_000, (FRAMES, OBS_DIM), TASK.action_dim, seed=seed)
    goal_reward = make_goal_reward(reward, config, seed=seed)
    report = load_logs(paths, buffer, goal_reward, config)
    task = report.task or TASK
    summary = {"episodes_used": report.episodes_used, "transitions": report.transitions,
               "skipped": report.skipped, "files": report.files, "reward": reward,
               "algo": "td3+bc" if bc else "td3", "updates": 0, "task": task.to_dict()}
    if report.transitions == 0:
        why = "; ".join(f"{reason} (x{n})" if n > 1 else reason
                        for reason, n in report.skipped.items()) or "no episodes in them"
        raise ValueError(f"no usable episodes in {', '.join(map(str, paths))}: {why}")
    agent = (TD3BC if bc else TD3)(TD3Config(seed=seed))
    agent.task = task.to_dict()  # the logs' task, recorded in its actor file
    if init_actor is not None:
        from policy.algorithms.td3 import load_actor

        agent.actor.load_state_dict(load_actor(init_actor, task=task).state_dict())
        agent.actor_target.load_state_dict(agent.actor.state_dict())
    with flush_denormals():  # Adam's moments of dead units: see policy.algorithms.td3
        for _ in tqdm(range(updates), unit="upd",
                      desc=f"{summary['algo']}+{reward} from logs"):
            agent.update(buffer.sample(agent.config.batch_size))
    summary["updates"] = updates
    out.mkdir(parents=True, exist_ok=True)
    agent.save_actor(out / "actor.pt")
    (out / "from_logs.json").write_text(json.dumps(summary, indent=2))
    return summary
