"""Replay buffer: ring wrap-around, episode ranges, base rewards, terminal vs truncation,
sampling and checkpoints."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from policy.replay import ReplayBuffer
from policy.rewards import EqualGoalReward, TraditionalReward


def _s(v: float) -> np.ndarray:
    return np.full((3, 35), v, np.float32)


def _fill(buf: ReplayBuffer, rewards, first_value: float = 0.0, terminal_last=True):
    for t, r in enumerate(rewards):
        last = t == len(rewards) - 1
        buf.add(_s(first_value + t), np.full(4, t, np.float32), r, _s(first_value + t + 1),
                terminal=terminal_last and last)
    return buf.end_episode()


def test_add_and_sample_shapes():
    buf = ReplayBuffer(capacity=100, seed=0)
    _fill(buf, [1.0, 2.0, 3.0])
    assert len(buf) == 3
    b = buf.sample(8)
    assert b.state.shape == (8, 105) and b.next_state.shape == (8, 105)
    assert b.action.shape == (8, 4) and b.reward.shape == (8, 1) and b.done.shape == (8, 1)
    assert b.state.dtype == torch.float32
    # consistency of a sampled row: next_state = state + 1, action = state value
    np.testing.assert_allclose(b.next_state[:, 0], b.state[:, 0] + 1)
    np.testing.assert_allclose(b.action[:, 0], b.state[:, 0])
    np.testing.assert_allclose(b.reward[:, 0], b.state[:, 0] + 1)


def test_truncation_is_not_terminal():
    buf = ReplayBuffer(capacity=10)
    ep = _fill(buf, [0.1] * 4, terminal_last=False)  # time limit: episode ends, not terminal
    np.testing.assert_array_equal(buf.episode_dones(ep), [0, 0, 0, 0])
    ep = _fill(buf, [0.1] * 3, terminal_last=True)  # collision/goal
    np.testing.assert_array_equal(buf.episode_dones(ep), [0, 0, 1])


def test_episode_ranges_and_wrap_around():
    buf = ReplayBuffer(capacity=5)
    ep0 = _fill(buf, [1, 2, 3])
    assert (ep0.start, ep0.length) == (0, 3)
    np.testing.assert_array_equal(buf.indices(ep0), [0, 1, 2])
    ep1 = _fill(buf, [4, 5, 6], first_value=10)
    assert (ep1.start, ep1.length) == (3, 3)
    np.testing.assert_array_equal(buf.indices(ep1), [3, 4, 0])  # wraps past the end
    assert len(buf) == 5 and buf.ptr == 1
    np.testing.assert_allclose(buf.episode_base_rewards(ep1), [4, 5, 6])
    np.testing.assert_allclose(buf.episode_states(ep1)[:, 0, 0], [10, 11, 12])
    with pytest.raises(KeyError):  # slot 0 of episode 0 was overwritten
        buf.indices(ep0)
    # rewriting touches exactly the wrapped slots
    TraditionalReward().on_episode_end(buf, ep1, reached_goal=True)
    np.testing.assert_allclose(buf._reward[:, 0], [56, 2, 3, 4, 5])
    np.testing.assert_allclose(buf._base_reward, [6, 2, 3, 4, 5])


def test_episode_longer_than_capacity_keeps_its_tail():
    buf = ReplayBuffer(capacity=4)
    ep = _fill(buf, [1, 2, 3, 4, 5, 6])
    assert ep.length == 4
    np.testing.assert_allclose(buf.episode_base_rewards(ep), [3, 4, 5, 6])


def test_variants_rewrite_from_base():
    buf = ReplayBuffer(capacity=10)
    ep = _fill(buf, [1.0, 2.0])
    egr = EqualGoalReward()
    egr.on_episode_end(buf, ep, True)
    egr.on_episode_end(buf, ep, True)
    np.testing.assert_allclose(buf.episode_rewards(ep), [2.0, 3.0])
    np.testing.assert_allclose(buf.episode_base_rewards(ep), [1.0, 2.0])
    with pytest.raises(ValueError):
        buf.set_episode_rewards(ep, np.zeros(3))


def test_sampling_is_seeded_and_uniform():
    a, b = ReplayBuffer(capacity=50, seed=3), ReplayBuffer(capacity=50, seed=3)
    for buf in (a, b):
        _fill(buf, list(range(40)))
    torch.testing.assert_close(a.sample(16).state, b.sample(16).state)
    counts = np.bincount(a.sample(40_000).reward[:, 0].long().numpy(), minlength=40)
    assert counts.min() > 800 and counts.max() < 1200  # ~1000 each


def _roundtrip(state):
    f = io.BytesIO()
    torch.save(state, f)
    f.seek(0)
    return torch.load(f, weights_only=True)


@pytest.mark.parametrize("capacity", [5, 64])
def test_state_dict_roundtrip(capacity):
    buf = ReplayBuffer(capacity=capacity, seed=1)
    _fill(buf, [1, 2, 3])
    _fill(buf, [4, 5, 6], first_value=10)
    buf.add(_s(50), np.zeros(4), 7.0, _s(51), False)  # open episode
    sd = _roundtrip(buf.state_dict())
    assert sd["state"].shape[0] == min(7, capacity)  # only the filled part
    new = ReplayBuffer(capacity=capacity, seed=99)
    new.load_state_dict(sd)
    assert len(new) == len(buf)
    torch.testing.assert_close(new.sample(32), buf.sample(32))
    # the open episode continues where it was
    new.add(_s(51), np.zeros(4), 8.0, _s(52), True)
    buf.add(_s(51), np.zeros(4), 8.0, _s(52), True)
    e_new, e_old = new.end_episode(), buf.end_episode()
    np.testing.assert_allclose(new.episode_base_rewards(e_new), [7, 8])
    np.testing.assert_allclose(buf.episode_base_rewards(e_old), [7, 8])
    assert e_new.id == e_old.id


def test_load_into_larger_buffer_is_chronological():
    small = ReplayBuffer(capacity=5)
    _fill(small, [1, 2, 3])
    _fill(small, [4, 5, 6])  # wrapped: ring holds 6,2,3,4,5
    big = ReplayBuffer(capacity=20)
    big.load_state_dict(small.state_dict())
    np.testing.assert_allclose(big._base_reward[:5], [2, 3, 4, 5, 6])
    assert big.ptr == 5 and len(big) == 5
