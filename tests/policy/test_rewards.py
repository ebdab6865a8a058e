"""Eq. 3.5 and the goal-reward variants (TR, NGR, EGR) on hand-worked episodes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from policy.algorithms.agents import make_goal_reward
from policy.algorithms.rewards import (
    EqualGoalReward,
    NoGoalReward,
    RewardConfig,
    TraditionalReward,
    base_reward,
    collision_reward,
    fold_angle,
)


def test_defaults_are_the_papers():
    c = RewardConfig()
    assert (c.w1, c.w2, c.w3, c.w4) == (8, 1, 1, 0.5)
    assert c.flight_level == 3.5 and c.collision == -50.0
    assert c.goal_tr == 50.0 and c.egr_bonus == 1.0 and c.paper_literal is False


def test_fold_angle():
    assert fold_angle(0) == 0 and fold_angle(180) == 180
    assert fold_angle(181) == 179 and fold_angle(350) == 10 and fold_angle(90) == 90


def test_base_reward_hand_worked():
    # D 10 -> 9.5, z = 3.0, h = 350 deg (v_h = 10), g = 300 deg (v_g = 60)
    total, parts = base_reward(10.0, 9.5, 3.0, 350.0, 300.0, RewardConfig())
    assert parts["progress"] == pytest.approx(8 * 0.5)
    assert parts["altitude"] == pytest.approx(-0.5 / 3.5)
    assert parts["heading"] == pytest.approx(1 - 10 / 180)
    assert parts["velocity_heading"] == pytest.approx(0.5 * (1 - 60 / 180))
    assert set(parts) == {"progress", "altitude", "heading", "velocity_heading"}
    assert total == pytest.approx(4 - 0.5 / 3.5 + 17 / 18 + 1 / 3)
    assert total == pytest.approx(sum(parts.values()))


def test_base_reward_paper_literal_last_term():
    total, parts = base_reward(10.0, 9.5, 3.0, 350.0, 300.0, RewardConfig(paper_literal=True))
    assert parts["velocity_heading"] == pytest.approx(0.5 * 60 / 180)
    assert total == pytest.approx(4 - 0.5 / 3.5 + 17 / 18 + 1 / 6)


def test_base_reward_best_and_worst_orientation():
    c = RewardConfig()
    # at flight level, facing and flying at the goal, no progress: w3 + w4
    total, _ = base_reward(5.0, 5.0, 3.5, 0.0, 0.0, c)
    assert total == pytest.approx(1.5)
    # facing and flying away (180 deg), above the flight level by 7 m, moving away 1 m
    total, parts = base_reward(5.0, 6.0, 10.5, 180.0, 180.0, c)
    assert parts["heading"] == 0 and parts["velocity_heading"] == 0
    assert total == pytest.approx(-8 - 2)
    assert math.isclose(base_reward(5, 5, 3.5, 181, 0, c)[1]["heading"], 1 / 180)


def test_collision_reward():
    r, parts = collision_reward(RewardConfig())
    assert r == -50.0 and parts["collision"] == -50.0


class FakeStore:
    """Minimal EpisodeStore: one episode, rewards rewritten in place."""

    def __init__(self, base):
        self.base = np.asarray(base, dtype=np.float32)
        self.reward = self.base.copy()

    def episode_base_rewards(self, episode):
        return self.base.copy()

    def episode_states(self, episode):
        return np.zeros((len(self.base), 3, 35), np.float32)

    def set_episode_rewards(self, episode, rewards):
        self.reward[:] = rewards


BASE = [1.0, -0.5, 2.0, 0.25]


def test_tr_adds_goal_reward_to_last_transition_only():
    store = FakeStore(BASE)
    TraditionalReward().on_episode_end(store, None, reached_goal=True)
    np.testing.assert_allclose(store.reward, [1.0, -0.5, 2.0, 50.25])
    store = FakeStore(BASE)
    TraditionalReward(RewardConfig(tr_replace=True)).on_episode_end(store, None, True)
    np.testing.assert_allclose(store.reward, [1.0, -0.5, 2.0, 50.0])


def test_ngr_keeps_base():
    store = FakeStore(BASE)
    NoGoalReward().on_episode_end(store, None, reached_goal=True)
    np.testing.assert_allclose(store.reward, BASE)


def test_egr_adds_one_everywhere():
    store = FakeStore(BASE)
    EqualGoalReward().on_episode_end(store, None, reached_goal=True)
    np.testing.assert_allclose(store.reward, [2.0, 0.5, 3.0, 1.25])


@pytest.mark.parametrize("name", ["tr", "ngr", "egr"])
def test_no_goal_means_base_rewards(name):
    store = FakeStore(BASE)
    store.reward[:] = 123.0  # stale rewards are rewritten from base
    make_goal_reward(name).on_episode_end(store, None, reached_goal=False)
    np.testing.assert_allclose(store.reward, BASE)


def test_rewrite_is_from_base_not_cumulative():
    store = FakeStore(BASE)
    egr = EqualGoalReward()
    egr.on_episode_end(store, None, True)
    egr.on_episode_end(store, None, True)
    np.testing.assert_allclose(store.reward, np.asarray(BASE) + 1)


def test_unknown_variant():
    with pytest.raises(ValueError):
        make_goal_reward("xyz")
