"""ABR (paper section 3.3, Algorithm 3.1) on hand-worked episodes."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from perception.observation import FrameStacker
from policy.algorithms.abr import (
    ABRConfig,
    AugmentativeBackwardReward,
    FeatureCNN,
    cosine_similarity,
)
from policy.algorithms.agents import make_goal_reward
from policy.algorithms.replay import ReplayBuffer

E1 = np.eye(20, dtype=np.float32)[0]
E2 = np.eye(20, dtype=np.float32)[1]


def _tilted(cos: float) -> np.ndarray:
    """A unit vector at cosine ``cos`` from E1."""
    return (cos * E1 + np.sqrt(1 - cos**2) * E2).astype(np.float32)


class ScriptedABR(AugmentativeBackwardReward):
    """ABR whose CNN features are scripted, one tau per group, to steer the patterns."""

    def __init__(self, taus=()):
        super().__init__()
        self.taus = list(taus)

    def features(self, states):
        out, self.taus = np.stack(self.taus[: len(states)]), self.taus[len(states):]
        return out


def _states(t: int) -> np.ndarray:
    return np.zeros((t, 3, 35), np.float32)


def test_cosine_similarity():
    h = np.stack([E1, E2, _tilted(0.5), np.zeros(20, np.float32)])
    np.testing.assert_allclose(cosine_similarity(E1, h), [1, 0, 0.5, 0], atol=1e-7)
    np.testing.assert_allclose(cosine_similarity(np.zeros(20), h), [0, 0, 0, 1])


def test_new_pattern_below_threshold_reused_above():
    abr = AugmentativeBackwardReward()
    assert abr.match(E1)[:2] == (0, True)  # empty history -> new
    assert abr.match(_tilted(0.99))[:2] == (0, False)  # 0.99 >= 0.98 -> reuse pattern 0
    assert abr.match(_tilted(0.98))[:2] == (0, False)  # threshold itself -> reuse
    j, new, zeta = abr.match(_tilted(0.97))  # 0.97 < 0.98 -> new pattern
    assert (j, new) == (1, True) and zeta == pytest.approx(0.97)
    assert len(abr.patterns) == 2 and len(abr.returns) == 2
    np.testing.assert_allclose(abr.patterns[1], _tilted(0.97))
    # the new pattern is itself matched from now on (argmax)
    assert abr.match(_tilted(0.97))[:2] == (1, False)


def test_sorted_distinct_return_sets_and_ranks():
    abr = AugmentativeBackwardReward()
    abr.match(E1)
    assert [abr.rank(0, r) for r in (2, 1, 5, 2, -1, 3)] == [0, 0, 2, 1, 0, 3]
    assert abr.returns[0] == [-1, 1, 2, 3, 5]


def test_hand_worked_episodes():
    abr = ScriptedABR()
    # Episode A, T = 7: groups (1..3), (4..6); transition 7 is a leftover.
    base_a = np.array([1.2, 0.5, 0.7, -0.4, 2.0, 0.1, 3.0])
    abr.taus = [E1, E1]
    r = abr.episode_rewards(base_a, _states(7), reached_goal=True)
    # R_1 = floor(2.4) = 2 -> set {2}, m = 0; R_2 = floor(1.7) = 1 -> {1, 2}, m = 0
    np.testing.assert_allclose(r, base_a)
    assert [(g.pattern, g.new_pattern, g.ret, g.rank) for g in abr.last_groups] == [
        (0, True, 2, 0), (0, False, 1, 0)]
    assert abr.returns == [[1, 2]]

    # Episode B, T = 8: group 1 like pattern 0 (cos 0.99), group 2 new (cos 0.5).
    base_b = np.array([2.0, 2.0, 1.5, 0.0, 0.0, 0.5, -7.0, 9.0])
    abr.taus = [_tilted(0.99), _tilted(0.5)]
    r = abr.episode_rewards(base_b, _states(8), reached_goal=True)
    # R_1 = floor(5.5) = 5 -> pattern 0: {1, 2, 5}, m = 2 -> +0.2 on transitions 1..3
    # R_2 = floor(0.5) = 0 -> new pattern 1: {0}, m = 0 -> +0 on 4..6; 7, 8 leftovers
    np.testing.assert_allclose(r, base_b + [0.2, 0.2, 0.2, 0, 0, 0, 0, 0])
    assert abr.returns == [[1, 2, 5], [0]]

    # Episode C, T = 6 (goal transition closes group 2): duplicate and negative returns.
    base_c = np.array([1.0, 0.5, 0.5, -0.2, -0.2, -0.1])
    abr.taus = [E1, _tilted(0.5)]
    r = abr.episode_rewards(base_c, _states(6), reached_goal=True)
    # R_1 = 2 (already in {1, 2, 5}) -> m = 1 -> +0.1 on 1..3
    # R_2 = floor(-0.5) = -1 -> pattern 1: {-1, 0}, m = 0 -> +0 on 4..6 (goal keeps base)
    np.testing.assert_allclose(r, base_c + [0.1, 0.1, 0.1, 0, 0, 0])
    assert abr.returns == [[1, 2, 5], [-1, 0]]
    assert r[-1] == pytest.approx(base_c[-1])  # no +50 goal chunk


def test_bonus_goes_to_exactly_the_group_and_leftovers_untouched():
    abr = ScriptedABR()
    abr.match(E1)
    abr.returns[0] = [-10, -5, 0]  # seeded history: a return of 7 ranks m = 3
    base = np.array([3.0, 2.0, 2.5, 0.1, 0.2])  # T = 5: one group, two leftovers
    abr.taus = [E1]
    r = abr.episode_rewards(base, _states(5), reached_goal=True)
    np.testing.assert_allclose(r, [3.3, 2.3, 2.8, 0.1, 0.2])
    assert abr.last_groups[0].rank == 3 and abr.last_groups[0].bonus == pytest.approx(0.3)


def test_short_and_failed_episodes_change_nothing():
    abr = AugmentativeBackwardReward()
    np.testing.assert_allclose(abr.episode_rewards([1.0, 2.0], _states(2), True), [1, 2])
    np.testing.assert_allclose(abr.episode_rewards([1.0] * 9, _states(9), False), [1] * 9)
    assert len(abr.patterns) == 0 and abr.returns == []


def test_cnn_shape_and_seed():
    cfg = ABRConfig()
    a, b, c = FeatureCNN(cfg), FeatureCNN(cfg), FeatureCNN(ABRConfig(seed=1))
    for (na, pa), pb in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        torch.testing.assert_close(pa, pb, msg=na)
    assert not torch.equal(a.conv.weight, c.conv.weight)
    assert a.conv.weight.shape == (32, 35, 2) and a.fc.weight.shape == (20, 64)
    out = a(torch.randn(7, 3, 35))
    assert out.shape == (7, 20) and (out >= 0).all()
    # building the CNN does not disturb the global RNG
    torch.manual_seed(5)
    x = torch.rand(3)
    torch.manual_seed(5)
    FeatureCNN(cfg)
    torch.testing.assert_close(torch.rand(3), x)


def _roundtrip(state):
    f = io.BytesIO()
    torch.save(state, f)
    f.seek(0)
    return torch.load(f, weights_only=True)


def test_state_dict_roundtrip_through_buffer():
    rng = np.random.default_rng(0)
    buf = ReplayBuffer(capacity=64)
    abr = make_goal_reward("abr")
    for _ in range(3):  # three goal episodes of 12 steps through the real CNN
        stacker = FrameStacker(3, 35)  # the buffer takes frame stacks
        state = stacker.push(rng.normal(size=35))
        for _t in range(12):
            next_state = stacker.push(rng.normal(size=35))
            buf.add(state, rng.normal(size=4), rng.normal(), next_state, False)
            state = next_state
        abr.on_episode_end(buf, buf.end_episode(), reached_goal=True)
    assert len(abr.patterns) >= 1
    restored = AugmentativeBackwardReward(ABRConfig(seed=123))  # different CNN, overwritten
    restored.load_state_dict(_roundtrip(abr.state_dict()))
    np.testing.assert_array_equal(restored.patterns, abr.patterns)
    assert restored.returns == abr.returns
    torch.testing.assert_close(restored.cnn.state_dict(), abr.cnn.state_dict())
    # both continue identically
    base, states = rng.normal(size=9) * 3, rng.normal(size=(9, 3, 35)).astype(np.float32)
    np.testing.assert_allclose(restored.episode_rewards(base, states, True),
                               abr.episode_rewards(base, states, True))
    assert restored.returns == abr.returns


def test_abr_rewrites_buffer_range():
    buf = ReplayBuffer(capacity=8)
    for _t in range(5):  # filler episode so the goal episode wraps around
        buf.add(np.zeros((3, 35)), np.zeros(4), 0.0, np.zeros((3, 35)), False)
    buf.end_episode()
    abr = ScriptedABR()
    abr.match(E1)
    abr.returns[0] = [0]
    base = [1.0, 1.0, 1.0, 0.5]
    for r in base:
        buf.add(np.ones((3, 35)), np.zeros(4), r, np.ones((3, 35)), False)
    ep = buf.end_episode()
    abr.taus = [E1]
    abr.on_episode_end(buf, ep, reached_goal=True)  # R_1 = 3 -> {0, 3}, m = 1
    np.testing.assert_array_equal(buf.indices(ep), [5, 6, 7, 0])
    np.testing.assert_allclose(buf.stored_rewards(ep), [1.1, 1.1, 1.1, 0.5])
    np.testing.assert_allclose(buf.episode_base_rewards(ep), base)
