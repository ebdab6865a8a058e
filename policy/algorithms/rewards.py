"""Rewards: the per-step base reward (paper eq. 3.5) and the goal-reward variants.

Reference: Chansuparp & Jitkajornwanich (2022), section 3.3 and Table 4.1, as pinned down
in ``shared/reference/abr-method.md``.

Per step, when not collided (eq. 3.5)::

    r = w1 (D_pre - D_cur)                       progress towards the goal
      + w2 (-|z - p_approAlt| / p_approAlt)      stay at the flight level
      + w3 (1 - v_h / 180)                       head towards the goal
      + w4 (1 - v_g / 180)                       fly (velocity) towards the goal

    v_x = 360 - x if x > 180 else x              (x in degrees, [0, 360))

On collision the reward is ``RewardConfig.collision`` (-50) and the episode is terminal.
:func:`step_reward` computes both cases from a step's :class:`bus.task.StepRecord`
(what the simulator's episode core says of the step, live or logged): the env, training,
rollouts and training from logs take their per-step reward from it.

Goal-reward variants (what happens to an episode's rewards when it reached the goal),
all applied when the episode ends by rewriting the rewards of its transitions in the
replay buffer, always starting from the stored *base* rewards:

=====  ========================================================================
TR     the last (goal) transition gets ``goal_tr`` (+50)
NGR    nothing extra
EGR    every transition of the episode gets ``egr_bonus`` (+1)
ABR    rank-based bonus per trajectory pattern (``abr.AugmentativeBackwardReward``)
=====  ========================================================================

This module is numpy-only (no torch) so the environment can import it cheaply.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from bus.task import StepRecord

__all__ = [
    "RewardConfig",
    "base_reward",
    "collision_reward",
    "step_reward",
    "fold_angle",
    "EpisodeStore",
    "GoalReward",
    "TraditionalReward",
    "NoGoalReward",
    "EqualGoalReward",
    "GOAL_REWARDS",
]


@dataclass
class RewardConfig:
    """Weights and constants of eq. 3.5 and of the goal-reward variants (paper Table 4.1).

    Attributes:
        w1..w4: weights of the progress, altitude, heading and velocity-heading terms.
        flight_level: p_approAlt, the appropriate altitude in metres (3.5).
        collision: reward of a collision transition (-50, terminal).
        goal_tr: TR's goal reward (+50) on the last transition of a goal episode.
        egr_bonus: EGR's equal reward (+1) added to every transition of a goal episode.
        paper_literal: **[choice]** the paper prints the last term of eq. 3.5 as
            ``w4 (v_g / 180)``, which with g defined as the angle between the velocity and
            the goal direction rewards flying away from the goal. By default we use
            ``w4 (1 - v_g / 180)``; ``paper_literal=True`` keeps the printed form.
        tr_replace: **[choice]** the paper's traditional reward has three cases (goal: +50,
            collision: -50, otherwise eq. 3.5), i.e. the goal transition's reward *is* +50.
            abr-method.md says the goal transition "gets +50"; by default (False) TR adds
            ``goal_tr`` to the goal transition's base reward, so TR differs from NGR only by
            the +50. ``tr_replace=True`` sets the goal transition's reward to ``goal_tr``.
    """

    w1: float = 8.0
    w2: float = 1.0
    w3: float = 1.0
    w4: float = 0.5
    flight_level: float = 3.5
    collision: float = -50.0
    goal_tr: float = 50.0
    egr_bonus: float = 1.0
    paper_literal: bool = False
    tr_replace: bool = False


def fold_angle(x_deg: float) -> float:
    """Eq. 3.5's v_x: fold an angle in [0, 360) degrees to [0, 180] (360 - x if x > 180)."""
    x = float(x_deg)
    return 360.0 - x if x > 180.0 else x


def base_reward(
    d_prev: float,
    d_cur: float,
    z: float,
    h_deg: float,
    g_deg: float,
    config: RewardConfig,
) -> tuple[float, dict[str, float]]:
    """Eq. 3.5, the per-step reward when not collided.

    Args:
        d_prev: D_pre, distance UAV-goal (m) before the step.
        d_cur: D_cur, distance UAV-goal (m) after the step.
        z: altitude (m).
        h_deg: angle in [0, 360) from the UAV's heading to the goal's horizontal direction.
        g_deg: **[choice]** angle in [0, 360) between the UAV's horizontal velocity and the
            goal's horizontal direction.
        config: weights; see ``RewardConfig.paper_literal`` for the last term.

    Returns:
        ``(total, components)`` with the four *weighted* terms by name: ``progress``,
        ``altitude``, ``heading``, ``velocity_heading``; ``total`` is their sum.
    """
    c = config
    v_h = fold_angle(h_deg)
    v_g = fold_angle(g_deg)
    progress = c.w1 * (float(d_prev) - float(d_cur))
    altitude = c.w2 * (-abs(float(z) - c.flight_level) / c.flight_level)
    heading = c.w3 * (1.0 - v_h / 180.0)
    if c.paper_literal:
        velocity_heading = c.w4 * (v_g / 180.0)
    else:
        velocity_heading = c.w4 * (1.0 - v_g / 180.0)
    parts = {
        "progress": progress,
        "altitude": altitude,
        "heading": heading,
        "velocity_heading": velocity_heading,
    }
    return progress + altitude + heading + velocity_heading, parts


def collision_reward(config: RewardConfig) -> tuple[float, dict[str, float]]:
    """Eq. 3.5's first case: ``r_collided`` (-50), with the same component names as
    ``base_reward`` (all zero) plus ``collision``."""
    parts = {"progress": 0.0, "altitude": 0.0, "heading": 0.0, "velocity_heading": 0.0}
    parts["collision"] = float(config.collision)
    return float(config.collision), parts


def step_reward(record: StepRecord, config: RewardConfig) -> tuple[float, dict[str, float]]:
    """Eq. 3.5 of one step from its record alone: ``r_collided`` (:func:`collision_reward`)
    when ``record.collided``, else :func:`base_reward` (D_pre = ``distance_before``,
    D_cur = ``distance``, z = ``altitude``, ``h``, ``g``)."""
    if record.collided:
        return collision_reward(config)
    return base_reward(record.distance_before, record.distance, record.altitude,
                       record.h, record.g, config)


# --------------------------------------------------------------------------- variants


class EpisodeStore(Protocol):
    """What a goal-reward variant needs from the replay buffer (``policy.algorithms.replay``)."""

    def episode_base_rewards(self, episode: Any) -> np.ndarray: ...

    def episode_states(self, episode: Any) -> np.ndarray: ...

    def set_episode_rewards(self, episode: Any, rewards: np.ndarray) -> None: ...


class GoalReward:
    """Base class of the goal-reward variants.

    Subclasses implement ``episode_rewards``: the full reward sequence of one finished
    episode computed from its base rewards (and, for ABR, its states). ``on_episode_end``
    writes that sequence back into the replay buffer into the episode's slots.
    Episodes that did not reach the goal keep their base rewards in every variant.
    """

    name: str = ""
    #: whether ``episode_rewards`` needs the episode's states (ABR does)
    needs_states: bool = False

    def episode_rewards(
        self, base: np.ndarray, states: np.ndarray | None, reached_goal: bool
    ) -> np.ndarray:
        raise NotImplementedError

    def on_episode_end(self, buffer: EpisodeStore, episode: Any, reached_goal: bool) -> np.ndarray:
        """Rewrite the rewards of ``episode`` in ``buffer`` from its base rewards.

        Returns the rewards written (float32, one per transition, in episode order).
        """
        base = buffer.episode_base_rewards(episode)
        states = buffer.episode_states(episode) if (reached_goal and self.needs_states) else None
        rewards = np.asarray(self.episode_rewards(base, states, reached_goal), dtype=np.float32)
        buffer.set_episode_rewards(episode, rewards)
        return rewards

    def __init__(self, config: RewardConfig | None = None) -> None:
        self.config = config or RewardConfig()

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        return None


class TraditionalReward(GoalReward):
    """TR: the last (goal) transition gets ``goal_tr`` (+50); see ``RewardConfig.tr_replace``."""

    name = "tr"

    def episode_rewards(
        self, base: np.ndarray, states: np.ndarray | None, reached_goal: bool
    ) -> np.ndarray:
        r = np.array(base, dtype=np.float64)
        if reached_goal and r.size:
            if self.config.tr_replace:
                r[-1] = self.config.goal_tr
            else:
                r[-1] += self.config.goal_tr
        return r


class NoGoalReward(GoalReward):
    """NGR: no goal reward; the episode keeps its base rewards."""

    name = "ngr"

    def episode_rewards(
        self, base: np.ndarray, states: np.ndarray | None, reached_goal: bool
    ) -> np.ndarray:
        return np.array(base, dtype=np.float64)


class EqualGoalReward(GoalReward):
    """EGR: every transition of a goal episode gets ``egr_bonus`` (+1) on top of its base."""

    name = "egr"

    def episode_rewards(
        self, base: np.ndarray, states: np.ndarray | None, reached_goal: bool
    ) -> np.ndarray:
        r = np.array(base, dtype=np.float64)
        if reached_goal:
            r += self.config.egr_bonus
        return r


#: the goal-reward variants by name (``policy.algorithms.agents.make_goal_reward`` builds them)
GOAL_REWARDS = ("tr", "ngr", "egr", "abr")
