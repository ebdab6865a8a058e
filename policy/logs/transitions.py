"""Transitions of one episode from the *log contract*, shared by ``--from-logs`` and the
live learner (``skyloop learner``): both decode their messages into
:class:`EpisodeSteps` and call :func:`transitions_from_steps` and :func:`add_episode`.

The contract (see :mod:`policy.logs.offline` for the message side): an episode of ``T``
steps has the goal (from START), the outcome and ``T`` (from END), one 35-attribute
observation per step 0 .. T-1 (step T when the log has it), the true pose per step
0 .. T, and the policy's body-frame action of each step 0 .. T-1.

Episodes are taken only under the goal limits they were run with: START records them
(``EpisodeEvent``), and one run under another goal radius or altitude is refused.

Rewards (eq. 3.5, never read as numbers from the log, so one log serves every goal
reward and reward configuration):

- from the **step records** when the episode has them (``step_record``, one per step
  1 .. T, :class:`bus.task.StepRecord`; the simulator's episode core made them, as for
  the env's own rewards): :func:`policy.algorithms.rewards.step_reward` of each, the
  same numbers the env computed. They are checked against the recomputation below
  wherever the log has the observation (every step but a stack log's last): a record
  whose reward differs by more than :data:`RECORD_ATOL`, or whose outcome or collision
  contradicts END, refuses the episode (never trained on silently);
- recomputed, for logs without records (made before they existed): from the truth
  distances and altitude and the observation's h, g, un-scaled with the scaling the
  observations record (the perception's ``ObservationConfig``; stored in float32, so
  recomputed rewards agree with the env's to about 1e-5), the collision reward on a
  collision end.

Observations that do not record their scaling, or disagree on it within an episode, are
refused (with or without records: they are the states). States are the 3-frame stacks,
zero-padded at the start. numpy only (no torch, no bus session).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bus.messages import yaw_of
from bus.task import TASK, StepRecord, TaskSpec, goal_angles
from perception.observation import (
    FrameStacker,
    ObservationConfig,
    config_from_scaling,
    goal_slots,
    goal_terms,
)
from policy.algorithms.rewards import (
    GoalReward,
    RewardConfig,
    base_reward,
    collision_reward,
    step_reward,
)

OBS_DIM, FRAMES = TASK.obs_dim, TASK.frames  # bus.task
OUTCOMES = ("success", "collision", "timeout", "aborted")
#: How far a step record's reward may be from the one recomputed from the logged pose and
#: observation: h and g pass through float32 observation slots (about 2e-5 degrees, a
#: reward difference near 1e-7); anything beyond this is a record that does not describe
#: the logged step.
RECORD_ATOL = 1e-4

#: One true pose: position (3,), velocity (3,), quaternion (x, y, z, w) (4,).
Pose = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass
class EpisodeSteps:
    """One episode as the log contract has it, decoded (see the module docstring)."""

    goal: np.ndarray  # (3,) world ENU
    steps: int  # T
    outcome: str  # success, collision, timeout, aborted
    observations: dict[int, np.ndarray]  # step -> (35,) float32
    truth: list[Pose]  # T + 1 poses
    actions: list[tuple[float, float, float, float]]  # T body-frame actions
    scalings: list[dict[str, Any] | None]  # what each observation records (None: nothing)
    limits: dict[str, float] | None = None  # what START records (bus.messages.episode_limits)
    records: dict[int, StepRecord] | None = None  # step 1 .. T -> its record; None: none logged


@dataclass
class Transitions:
    """One episode rebuilt: T transitions."""

    states: np.ndarray  # (T, 3, 35) float32
    actions: np.ndarray  # (T, 4) float32
    rewards: np.ndarray  # (T,) base rewards
    next_states: np.ndarray  # (T, 3, 35)
    terminal: bool  # last transition terminal (goal or collision)
    reached: bool


def terminal_observation(previous: np.ndarray, pose: Pose, goal: np.ndarray,
                         scaling: ObservationConfig) -> np.ndarray:
    """The observation after the last step when the log has none (stack logs end the
    episode without a last scan): the previous faces, altitude and h, g from the
    terminal *true* pose (the env uses the estimate; they differ by centimetres and
    fractions of a degree), scaled as the episode's observations. Used for the last
    reward and next state only."""
    position, velocity, q = pose
    h, g = goal_angles(position, yaw_of(q), velocity, goal)
    out = np.array(previous, np.float32, copy=True)
    out[TASK.faces:TASK.obs_dim] = goal_slots(position[2], h, g, scaling)
    return out


def one_scaling(scalings: list[dict[str, Any] | None]) -> ObservationConfig:
    """The one scaling an episode's observations record (``bus.messages``
    ``observation_scaling`` of each); ``ValueError`` if one does not record it or they
    disagree."""
    recorded = [s for s in scalings if s is not None]
    if not scalings or len(recorded) != len(scalings):
        raise ValueError("observations without their scaling (Observation.radius 0): "
                         "rewards cannot be recomputed")
    distinct = {tuple(sorted(s.items())) for s in recorded}
    if len(distinct) != 1:
        raise ValueError(f"observations scaled {len(distinct)} ways within the episode")
    return config_from_scaling(recorded[0])


def transitions_from_steps(ep: EpisodeSteps, config: RewardConfig,
                           task: TaskSpec = TASK) -> Transitions:
    """Transitions of one complete episode for a learner of ``task``; ``ValueError`` names
    what does not fit, including an episode run under other goal limits than ``task``'s
    (``TaskSpec.limits_mismatch``: its success, terminal flag and goal reward would mean
    something else)."""
    T, obs, truth = ep.steps, dict(ep.observations), ep.truth
    if T is None or T < 1:
        raise ValueError("no steps")
    why = task.limits_mismatch(ep.limits)
    if why is not None:
        raise ValueError(f"episode {why}")
    scaling = one_scaling(ep.scalings)
    if ep.outcome not in OUTCOMES:
        raise ValueError(f"outcome {ep.outcome!r}")
    if len(truth) != T + 1 or len(ep.actions) != T:
        raise ValueError(f"{len(truth)} truth poses and {len(ep.actions)} actions for T = {T}")
    if sorted(obs) == list(range(T)):  # a stack log: no scan after the last step
        obs[T] = terminal_observation(obs[T - 1], truth[T], ep.goal, scaling)
    if sorted(obs) != list(range(T + 1)):
        raise ValueError(f"observations for steps {sorted(obs)[:3]}.. but T = {T}")
    logged = T in ep.observations  # the last observation is the log's, not made up
    stacker = FrameStacker(FRAMES, OBS_DIM)
    stacks = [stacker.push(obs[k]) for k in range(T + 1)]
    rewards = recomputed_rewards(ep, obs, scaling, config)
    if ep.records:
        rewards = record_rewards(ep, config, rewards, T if logged else T - 1)
    return Transitions(np.stack(stacks[:-1]), np.asarray(ep.actions, np.float32), rewards,
                       np.stack(stacks[1:]), ep.outcome in ("success", "collision"),
                       ep.outcome == "success")


def recomputed_rewards(ep: EpisodeSteps, obs: dict[int, np.ndarray],
                       scaling: ObservationConfig, config: RewardConfig) -> np.ndarray:
    """Eq. 3.5 of each step from the logged truth poses and the observations' h, g
    (``obs``: steps 0 .. T), the collision reward on a collision end: the rewards of a
    log without step records."""
    T, truth = ep.steps, ep.truth
    dist = [float(np.linalg.norm(p[0] - ep.goal)) for p in truth]
    rewards = np.empty(T)
    for k in range(T):
        if k == T - 1 and ep.outcome == "collision":
            rewards[k] = collision_reward(config)[0]
            continue
        _, h, g = goal_terms(obs[k + 1], scaling)
        rewards[k] = base_reward(dist[k], dist[k + 1], float(truth[k + 1][0][2]), h, g,
                                 config)[0]
    return rewards


def record_rewards(ep: EpisodeSteps, config: RewardConfig, recomputed: np.ndarray,
                   checked: int) -> np.ndarray:
    """Eq. 3.5 of each step from its record (``step_reward``); ``ValueError`` when the
    records do not cover steps 1 .. T, when one's outcome or collision contradicts END
    (the last may end the episode, as END says, or say nothing of an aborted one; none
    before it may), or when the reward of one of the first ``checked`` steps is more
    than :data:`RECORD_ATOL` from ``recomputed``."""
    T, records = ep.steps, ep.records or {}
    if sorted(records) != list(range(1, T + 1)):
        raise ValueError(f"step records for steps {sorted(records)[:3]}.. but T = {T}")
    rewards = np.empty(T)
    for k in range(1, T + 1):
        rec = records[k]
        expected = (None if ep.outcome == "aborted" else ep.outcome) if k == T else None
        if rec.outcome != expected or rec.collided != (expected == "collision"):
            raise ValueError(f"step record {k} says outcome {rec.outcome}, collided "
                             f"{rec.collided}; END says {ep.outcome} after {T} steps")
        rewards[k - 1] = step_reward(rec, config)[0]
        if k <= checked and abs(rewards[k - 1] - recomputed[k - 1]) > RECORD_ATOL:
            raise ValueError(f"step record {k} gives reward {rewards[k - 1]:.6g}, the "
                             f"logged pose and observation {recomputed[k - 1]:.6g}")
    return rewards


def add_episode(tr: Transitions, buffer, goal_reward: GoalReward) -> np.ndarray:
    """Store one rebuilt episode in a :class:`~policy.algorithms.replay.ReplayBuffer` and let the
    goal-reward variant (TR/NGR/EGR/ABR) rewrite its rewards; returns the rewards."""
    T = len(tr.actions)
    for k in range(T):
        buffer.add(tr.states[k], tr.actions[k], float(tr.rewards[k]), tr.next_states[k],
                   tr.terminal and k == T - 1)
    return goal_reward.on_episode_end(buffer, buffer.end_episode(), tr.reached)
