"""Replay buffer: ring wrap-around, episode slots, streams, base rewards, terminal vs
truncation, frame-stack checks, sampling (bit-identical to full stored states) and
checkpoints (compact and previous format)."""

from __future__ import annotations

import copy
import io
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
import torch

from policy.algorithms.replay import Batch, ReplayBuffer
from policy.algorithms.rewards import EqualGoalReward, TraditionalReward

FRAMES, ATTRS = 3, 35


class _FullStateReplay:
    """The previous implementation (full state and next_state per slot), trimmed to what
    the tests compare against: same slot assignment, same generator draws."""

    def __init__(self, capacity: int, state_shape=(3, 35), action_dim: int = 4,
                 seed: int = 0) -> None:
        self.capacity = int(capacity)
        self.state_shape = tuple(state_shape)
        self.state_dim = int(np.prod(self.state_shape))
        self.action_dim = int(action_dim)
        n = self.capacity
        self._state = np.zeros((n, self.state_dim), np.float32)
        self._next_state = np.zeros((n, self.state_dim), np.float32)
        self._action = np.zeros((n, self.action_dim), np.float32)
        self._reward = np.zeros((n, 1), np.float32)
        self._base_reward = np.zeros(n, np.float32)
        self._done = np.zeros((n, 1), np.float32)
        self._episode_id = np.full(n, -1, np.int64)
        self._t = tuple(torch.from_numpy(a) for a in (
            self._state, self._action, self._reward, self._next_state, self._done))
        self.ptr = 0
        self.size = 0
        self._next_episode_id = 0
        self._open_length = 0
        self.generator = torch.Generator().manual_seed(int(seed))

    def add(self, state, action, reward, next_state, terminal) -> int:
        i = self.ptr
        self._state[i] = np.reshape(state, -1)
        self._next_state[i] = np.reshape(next_state, -1)
        self._action[i] = np.reshape(action, -1)
        self._reward[i, 0] = reward
        self._base_reward[i] = reward
        self._done[i, 0] = 1.0 if terminal else 0.0
        self._episode_id[i] = self._next_episode_id
        self.ptr = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        self._open_length += 1
        return i

    def end_episode(self) -> None:
        self._next_episode_id += 1
        self._open_length = 0

    def sample(self, batch_size: int) -> Batch:
        idx = torch.randint(self.size, (batch_size,), generator=self.generator)
        s, a, r, s2, d = self._t
        return Batch(s[idx], a[idx], r[idx], s2[idx], d[idx])

    def state_dict(self) -> dict[str, Any]:
        if self.size < self.capacity:
            idx = np.arange(self.size)
        else:
            idx = (self.ptr + np.arange(self.capacity)) % self.capacity

        def take(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(a[idx])

        return {
            "state_shape": list(self.state_shape), "action_dim": self.action_dim,
            "state": take(self._state), "action": take(self._action),
            "reward": take(self._reward), "base_reward": take(self._base_reward),
            "next_state": take(self._next_state), "done": take(self._done),
            "episode_id": take(self._episode_id), "capacity": self.capacity,
            "ptr": self.ptr, "next_episode_id": self._next_episode_id,
            "open_length": self._open_length, "generator": self.generator.get_state(),
        }


# ------------------------------------------------------------------ episodes


def _stacks(obs: np.ndarray, first: np.ndarray | None = None) -> np.ndarray:
    """Frame stacks s_0..s_T of observations o_0..o_T (zeros before o_0, or the frames
    of ``first`` for an episode that does not start from zeros), (T+1, 3, 35)."""
    pad = np.zeros((FRAMES - 1, ATTRS), np.float32) if first is None else first[1:]
    seq = np.concatenate([pad, obs.astype(np.float32)])
    return np.stack([seq[k:k + FRAMES] for k in range(obs.shape[0])])


@dataclass
class _Ep:
    states: np.ndarray  # (T+1, 3, 35): transition k is (states[k], states[k+1])
    actions: np.ndarray
    rewards: np.ndarray
    terminal: bool
    t: int = 0  # next transition to add

    @property
    def steps(self) -> int:
        return self.actions.shape[0]


def _episode(rng: np.random.Generator, steps: int, zero_start: bool = True) -> _Ep:
    obs = rng.normal(size=(steps + 1, ATTRS)).astype(np.float32)
    first = None if zero_start else rng.normal(size=(FRAMES, ATTRS)).astype(np.float32)
    if first is not None:
        obs[0] = first[-1]
    return _Ep(_stacks(obs, first), rng.uniform(-2, 2, (steps, 4)).astype(np.float32),
               rng.normal(size=steps).astype(np.float32), bool(rng.integers(2)))


def _run(bufs, rng: np.random.Generator, adds: int, streams: int, max_steps: int = 12,
         on_add=None, open_: dict[int, _Ep] | None = None, on_end=None) -> dict[int, list]:
    """``adds`` transitions of random episodes on ``streams`` interleaved streams into
    ``ReplayBuffer``s and/or reference buffers (episode ids kept only with one stream);
    returns per stream the list of (Episode, _Ep) of the episodes closed. ``on_add(slot)``
    after each add, ``on_end(Episode, _Ep)`` after each end_episode; ``open_`` (stream ->
    _Ep) holds the open episodes, in and out."""
    open_ = {} if open_ is None else open_
    closed: dict[int, list] = {k: [] for k in range(streams)}
    for _ in range(adds):
        k = int(rng.integers(streams))
        if k not in open_:
            open_[k] = _episode(rng, int(rng.integers(1, max_steps + 1)),
                                zero_start=rng.random() < 0.8)
        ep = open_[k]
        t = ep.t
        args = (ep.states[t], ep.actions[t], float(ep.rewards[t]), ep.states[t + 1],
                ep.terminal and t == ep.steps - 1)
        slots = {buf.add(*args, stream=k) if isinstance(buf, ReplayBuffer) else buf.add(*args)
                 for buf in bufs}
        assert len(slots) == 1
        ep.t += 1
        if on_add is not None:
            on_add(slots.pop())
        if ep.t == ep.steps:
            episode = None
            for buf in bufs:
                if isinstance(buf, ReplayBuffer):
                    episode = buf.end_episode(stream=k)
                elif streams == 1:
                    buf.end_episode()
            closed[k].append((episode, open_.pop(k)))
            if on_end is not None:
                on_end(episode, ep)
    return closed


def _stored(buf: ReplayBuffer) -> tuple[np.ndarray, np.ndarray]:
    """Every filled slot's state and next_state, rebuilt from the frame pool."""
    n = buf.size
    s = buf._frames[buf._rows[0, :n]].reshape(n, -1)
    s2 = buf._frames[buf._rows[1, :n]].reshape(n, -1)
    return s, s2


def _same_batch(a: Batch, b: Batch) -> None:
    for x, y in zip(a, b, strict=True):
        assert x.dtype == y.dtype and x.shape == y.shape
        assert torch.equal(x, y)  # exact: the same float32 bits (no NaN in these tests)


def _s(v: float) -> np.ndarray:
    return np.full((3, 35), v, np.float32)


def _fill(buf: ReplayBuffer, rewards, first_value: float = 0.0, terminal_last=True,
          stream: int = 0):
    """An episode whose observations are all ``first_value + t`` (t = 0..T), starting
    from zeros; action = the step index."""
    obs = np.repeat(first_value + np.arange(len(rewards) + 1, dtype=np.float32)[:, None],
                    ATTRS, axis=1)
    states = _stacks(obs)
    for t, r in enumerate(rewards):
        last = t == len(rewards) - 1
        buf.add(states[t], np.full(4, t, np.float32), r, states[t + 1],
                terminal=terminal_last and last, stream=stream)
    return buf.end_episode(stream=stream)


# --------------------------------------------------------------------- basics


def test_add_and_sample_shapes():
    buf = ReplayBuffer(capacity=100, seed=0)
    _fill(buf, [1.0, 2.0, 3.0])
    assert len(buf) == 3
    b = buf.sample(8)
    assert b.state.shape == (8, 105) and b.next_state.shape == (8, 105)
    assert b.action.shape == (8, 4) and b.reward.shape == (8, 1) and b.done.shape == (8, 1)
    assert b.state.dtype == torch.float32
    assert all(x.is_contiguous() for x in b)
    # a sampled row: newest frame of next_state = state's + 1, action = state's value
    np.testing.assert_allclose(b.next_state[:, -35], b.state[:, -35] + 1)
    np.testing.assert_allclose(b.next_state[:, :70], b.state[:, 35:])
    np.testing.assert_allclose(b.action[:, 0], b.state[:, -35])
    np.testing.assert_allclose(b.reward[:, 0], b.state[:, -35] + 1)


def test_truncation_is_not_terminal():
    buf = ReplayBuffer(capacity=10)
    ep = _fill(buf, [0.1] * 4, terminal_last=False)  # time limit: episode ends, not terminal
    np.testing.assert_array_equal(buf.stored_dones(ep), [0, 0, 0, 0])
    ep = _fill(buf, [0.1] * 3, terminal_last=True)  # collision/goal
    np.testing.assert_array_equal(buf.stored_dones(ep), [0, 0, 1])


def test_episode_slots_and_wrap_around():
    buf = ReplayBuffer(capacity=5)
    ep0 = _fill(buf, [1, 2, 3])
    assert (ep0.id, ep0.length) == (0, 3)
    np.testing.assert_array_equal(buf.indices(ep0), [0, 1, 2])
    ep1 = _fill(buf, [4, 5, 6], first_value=10)
    assert (ep1.id, ep1.length) == (1, 3)
    np.testing.assert_array_equal(buf.indices(ep1), [3, 4, 0])  # wraps past the end
    assert len(buf) == 5 and buf.ptr == 1
    np.testing.assert_allclose(buf.episode_base_rewards(ep1), [4, 5, 6])
    states = buf.episode_states(ep1)
    assert states.shape == (3, 3, 35)
    np.testing.assert_allclose(states[:, :, 0], [[0, 0, 10], [0, 10, 11], [10, 11, 12]])
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
    np.testing.assert_allclose(buf.episode_states(ep)[:, :, 0],
                               [[0, 1, 2], [1, 2, 3], [2, 3, 4], [3, 4, 5]])


def test_variants_rewrite_from_base():
    buf = ReplayBuffer(capacity=10)
    ep = _fill(buf, [1.0, 2.0])
    egr = EqualGoalReward()
    egr.on_episode_end(buf, ep, True)
    egr.on_episode_end(buf, ep, True)
    np.testing.assert_allclose(buf.stored_rewards(ep), [2.0, 3.0])
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


def test_empty_episode_and_empty_buffer():
    buf = ReplayBuffer(capacity=4)
    with pytest.raises(ValueError, match="empty"):
        buf.sample(2)
    ep = buf.end_episode()
    assert (ep.id, ep.length) == (0, 0)
    assert buf.indices(ep).shape == (0,) and buf.episode_states(ep).shape == (0, 3, 35)
    assert _fill(buf, [1.0]).id == 1


# ------------------------------------------------------------- frame stacks


def test_inconsistent_stacks_are_refused():
    buf = ReplayBuffer(capacity=10)
    ep = _episode(np.random.default_rng(0), 4)
    buf.add(ep.states[0], ep.actions[0], 0.0, ep.states[1], False)
    with pytest.raises(ValueError, match=r"next_state\[:-1\] != state\[1:\]"):
        buf.add(ep.states[1], ep.actions[1], 0.0, ep.states[1], False)  # not shifted
    with pytest.raises(ValueError, match="previous next_state"):
        buf.add(ep.states[2], ep.actions[2], 0.0, ep.states[3], False)  # skips a step
    other = ep.states[1].copy()
    other[0, 0] = -0.0 if other[0, 0] == 0 else other[0, 0] + 1e-7  # any bit differs
    with pytest.raises(ValueError, match="previous next_state"):
        buf.add(other, ep.actions[1], 0.0, np.concatenate([other[1:], ep.states[2][-1:]]),
                False)
    with pytest.raises(ValueError, match="105 values"):
        buf.add(np.zeros(104), ep.actions[1], 0.0, np.zeros(105), False)
    with pytest.raises(ValueError):
        buf.add(ep.states[1], np.zeros(3), 0.0, ep.states[2], False)  # action_dim 4
    with pytest.raises(ValueError, match="stream 3"):
        buf.add(ep.states[1], ep.actions[1], 0.0, ep.states[1], False, stream=3)
    assert len(buf) == 1 and buf.ptr == 1  # nothing stored by a refused add
    assert buf.open_episode(stream=3).id == 1  # nor an episode opened
    buf.add(ep.states[1], ep.actions[1], 0.0, ep.states[2], False)  # the right one
    assert buf.open_episode().length == 2
    # another stream's episode is independent; a closed episode's next one may start anywhere
    buf.add(_s(7), np.zeros(4), 0.0, np.concatenate([_s(7)[1:], _s(8)[:1]]), False,
            stream=1)
    buf.end_episode()
    buf.add(_s(3), np.zeros(4), 0.0, np.concatenate([_s(3)[1:], _s(4)[:1]]), False)
    np.testing.assert_array_equal(buf.episode_states(buf.open_episode())[0], _s(3))


def test_first_state_from_logs_is_kept_whole():
    buf = ReplayBuffer(capacity=10)
    ep = _episode(np.random.default_rng(1), 5, zero_start=False)
    for t in range(ep.steps):
        buf.add(ep.states[t], ep.actions[t], 0.0, ep.states[t + 1], False)
    e = buf.end_episode()
    np.testing.assert_array_equal(buf.episode_states(e), ep.states[:-1])
    s, s2 = _stored(buf)
    np.testing.assert_array_equal(s2, ep.states[1:].reshape(5, -1))


def test_one_frame_states():
    buf = ReplayBuffer(capacity=3, state_shape=(4,), action_dim=1)
    obs = np.arange(20, dtype=np.float32).reshape(5, 4)
    for t in range(4):
        buf.add(obs[t], [t], 0.0, obs[t + 1], False)
    s, s2 = _stored(buf)
    np.testing.assert_array_equal(s[[1, 2, 0]], obs[1:4])  # slot 0 holds step 3
    np.testing.assert_array_equal(s2[[1, 2, 0]], obs[2:5])


# ----------------------------------------------- bit-identical to full states


@pytest.mark.parametrize(("streams", "seed"), [(1, 0), (2, 1), (3, 2)])
def test_batches_equal_full_state_buffer(streams, seed):
    """Same adds -> the same batches as the previous implementation (sampled between
    adds, as in training); episodes interleaved over streams."""
    new, ref = ReplayBuffer(capacity=2000, seed=seed), _FullStateReplay(2000, seed=seed)
    rng = np.random.default_rng(seed)
    sizes = iter(rng.integers(1, 130, size=10_000).tolist())

    def both(slot: int) -> None:
        if slot % 3 == 0:
            size = next(sizes)
            _same_batch(new.sample(size), ref.sample(size))

    _run([new, ref], rng, 1500, streams, max_steps=40, on_add=both)
    # both generators drew the same numbers: so they still agree batch by batch
    for _ in range(20):
        _same_batch(new.sample(100), ref.sample(100))
    s, s2 = _stored(new)
    np.testing.assert_array_equal(s, ref._state[:new.size])
    np.testing.assert_array_equal(s2, ref._next_state[:new.size])


@pytest.mark.parametrize(("capacity", "streams"), [(1, 1), (2, 2), (7, 3), (13, 2), (50, 3)])
def test_wrap_around_keeps_every_state_exact(capacity, streams):
    """Fill a small ring many times over with interleaved episodes (some longer than the
    ring): after every add each stored transition rebuilds to what was added, sampling
    matches the full-state buffer and episodes give their surviving slots."""
    new, ref = ReplayBuffer(capacity, seed=5), _FullStateReplay(capacity, seed=5)
    rng = np.random.default_rng(capacity)

    def check(slot: int) -> None:
        s, s2 = _stored(new)
        np.testing.assert_array_equal(s, ref._state[:new.size])
        np.testing.assert_array_equal(s2, ref._next_state[:new.size])
        if new.size == capacity:
            _same_batch(new.sample(16), ref.sample(16))
        for k in list(new._streams):  # open_episode(k) would open one
            ep = new.open_episode(stream=k)
            np.testing.assert_array_equal(new._episode_id[ep.slots], ep.id)

    ended, clock, written = [], [0], np.zeros(capacity, int)  # add count, when each slot

    def check_and_time(slot: int) -> None:
        clock[0] += 1
        written[slot] = clock[0]
        check(slot)

    def check_episode(episode, ep: _Ep) -> None:  # what survives of it, when it ends
        n = episode.length
        assert n == ep.steps or 0 < n <= capacity
        np.testing.assert_array_equal(new.episode_states(episode), ep.states[ep.steps - n:-1])
        np.testing.assert_array_equal(new.episode_base_rewards(episode), ep.rewards[-n:])
        ended.append((episode, clock[0]))

    _run([new, ref], rng, 40 * capacity + 30, streams, max_steps=max(2, 2 * capacity),
         on_add=check_and_time, on_end=check_episode)
    assert new._blocks_used <= capacity  # head blocks are recycled
    assert sum(e.length for e, _ in ended) > 10 * capacity
    for episode, at in ended:  # KeyError exactly when a slot was written again since
        if (written[episode.slots] <= at).all():
            np.testing.assert_array_equal(new.indices(episode), episode.slots)
        else:
            with pytest.raises(KeyError):
                new.indices(episode)


def test_streams_keep_separate_episodes():
    buf = ReplayBuffer(capacity=100)
    rng = np.random.default_rng(3)
    a, b = _episode(rng, 4), _episode(rng, 3)
    for t in range(4):  # interleave: a0 b0 a1 b1 a2 b2 a3
        buf.add(a.states[t], a.actions[t], float(t), a.states[t + 1], False, stream=0)
        if t < 3:
            buf.add(b.states[t], b.actions[t], 10.0 + t, b.states[t + 1], t == 2, stream=7)
    np.testing.assert_array_equal(buf.open_episode(stream=7).slots, [1, 3, 5])
    assert buf.open_streams() == [0, 7]
    eb = buf.end_episode(stream=7)
    assert buf.open_streams() == [0]
    ea = buf.end_episode()
    assert (ea.id, eb.id) == (0, 1)
    np.testing.assert_array_equal(buf.indices(ea), [0, 2, 4, 6])
    np.testing.assert_array_equal(buf.episode_states(ea), a.states[:4])
    np.testing.assert_array_equal(buf.episode_states(eb), b.states[:3])
    np.testing.assert_array_equal(buf.episode_base_rewards(eb), [10, 11, 12])
    np.testing.assert_array_equal(buf.stored_dones(eb), [0, 0, 1])
    TraditionalReward().on_episode_end(buf, eb, reached_goal=True)
    np.testing.assert_allclose(buf._reward[:7, 0], [0, 10, 1, 11, 2, 62, 3])


# ---------------------------------------------------------------- checkpoints


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
    s50 = _stacks(np.full((3, 35), 50, np.float32))
    buf.add(s50[0], np.zeros(4), 7.0, s50[1], False)  # open episode
    sd = _roundtrip(buf.state_dict())
    assert sd["obs"].shape[0] == min(7, capacity)  # only the filled part
    new = ReplayBuffer(capacity=capacity, seed=99)
    new.load_state_dict(sd)
    assert len(new) == len(buf)
    _same_batch(new.sample(32), buf.sample(32))
    # the open episode continues where it was
    new.add(s50[1], np.zeros(4), 8.0, s50[2], True)
    buf.add(s50[1], np.zeros(4), 8.0, s50[2], True)
    e_new, e_old = new.end_episode(), buf.end_episode()
    np.testing.assert_allclose(new.episode_base_rewards(e_new), [7, 8])
    np.testing.assert_allclose(buf.episode_base_rewards(e_old), [7, 8])
    assert e_new.id == e_old.id


@pytest.mark.parametrize("capacity", [9, 40])
def test_state_dict_continues_identically_with_streams(capacity):
    """Checkpoint mid-run (open episodes on 3 streams, ring wrapped or not); the restored
    buffer then behaves exactly like the original: states, batches, episodes."""
    rng = np.random.default_rng(capacity)
    buf = ReplayBuffer(capacity, seed=2)
    open_: dict[int, _Ep] = {}
    _run([buf], rng, 31, 3, max_steps=8, open_=open_)
    assert open_ and all(ep.t > 0 for ep in open_.values())
    restored = ReplayBuffer(capacity, seed=0)
    restored.load_state_dict(_roundtrip(buf.state_dict()))
    state = rng.bit_generator.state
    for b in (buf, restored):  # the same random continuation into both
        rng.bit_generator.state = state
        _run([b], rng, 60, 3, max_steps=8, open_=copy.deepcopy(open_))
        b.end_episode(stream=1)
    for x, y in zip(_stored(buf), _stored(restored), strict=True):
        np.testing.assert_array_equal(x, y)
    _same_batch(buf.sample(50), restored.sample(50))
    assert (restored.ptr, restored._next_episode_id) == (buf.ptr, buf._next_episode_id)
    assert restored.open_streams() == buf.open_streams()
    assert restored.open_episode(stream=2).id == buf.open_episode(stream=2).id
    np.testing.assert_array_equal(restored.open_episode(stream=2).slots,
                                  buf.open_episode(stream=2).slots)


def test_state_dict_open_streams_continue():
    rng = np.random.default_rng(4)
    buf = ReplayBuffer(6, seed=1)
    eps = [_episode(rng, 9) for _ in range(2)]
    for t in range(4):  # two open episodes, ring wrapped
        for k in (0, 1):
            buf.add(eps[k].states[t], eps[k].actions[t], 0.0, eps[k].states[t + 1], False,
                    stream=k)
    for capacity in (6, 3, 20):  # same ring, smaller (oldest dropped), larger
        new = ReplayBuffer(capacity)
        new.load_state_dict(_roundtrip(buf.state_dict()))
        assert len(new) == min(6, capacity)
        for k in (0, 1):
            with pytest.raises(ValueError):  # still checked against the open episode
                new.add(eps[k].states[5], eps[k].actions[5], 0.0, eps[k].states[6], False,
                        stream=k)
            for t in (4, 5):
                new.add(eps[k].states[t], eps[k].actions[t], 0.0, eps[k].states[t + 1],
                        False, stream=k)
        # ring before: a1 b1 a2 b2 a3 b3; then a4 a5 b4 b5 were added
        lengths = {6: (3, 3), 3: (1, 2), 20: (5, 5)}[capacity]
        for k in (0, 1):
            ep = new.end_episode(stream=k)
            assert (ep.id, ep.length) == (k, lengths[k])
            n = ep.length
            np.testing.assert_array_equal(new.episode_states(ep), eps[k].states[6 - n:6])
            np.testing.assert_array_equal(new.episode_base_rewards(ep), np.zeros(n))


def test_load_into_smaller_buffer_materializes_states():
    rng = np.random.default_rng(6)
    big, ref = ReplayBuffer(60), _FullStateReplay(60)
    _run([big, ref], rng, 45, 2, max_steps=10)
    for capacity in (1, 2, 3, 11):
        small = ReplayBuffer(capacity)
        small.load_state_dict(big.state_dict())
        s, s2 = _stored(small)
        np.testing.assert_array_equal(s, ref._state[45 - capacity:45])
        np.testing.assert_array_equal(s2, ref._next_state[45 - capacity:45])
        assert small.ptr == 0 and len(small) == capacity


def test_load_into_larger_buffer_is_chronological():
    small = ReplayBuffer(capacity=5)
    _fill(small, [1, 2, 3])
    _fill(small, [4, 5, 6])  # wrapped: ring holds 6,2,3,4,5
    big = ReplayBuffer(capacity=20)
    big.load_state_dict(small.state_dict())
    np.testing.assert_allclose(big._base_reward[:5], [2, 3, 4, 5, 6])
    assert big.ptr == 5 and len(big) == 5


@pytest.mark.parametrize(("capacity", "adds"), [(30, 25), (30, 71), (12, 40)])
def test_previous_format_state_dict_loads(capacity, adds):
    """A checkpoint of the previous implementation (full states) converts: same
    transitions, same ring, same sampling afterwards, the open episode continues."""
    rng = np.random.default_rng(adds)
    ref = _FullStateReplay(capacity, seed=4)
    eps = _run([ref], rng, adds, 1, max_steps=9)
    assert eps[0]
    ref.end_episode()  # the unfinished one of _run (its id is simply skipped)
    ep = _episode(rng, 5)  # open episode: 2 of 5 steps added
    for t in range(2):
        ref.add(ep.states[t], ep.actions[t], float(ep.rewards[t]), ep.states[t + 1], False)
    old = _roundtrip(ref.state_dict())
    for cap in (capacity, 7, 100):
        new = ReplayBuffer(cap, seed=0)
        new.load_state_dict(old)
        keep = min(cap, ref.size)
        s, s2 = _stored(new)
        slots = (new.ptr + np.arange(keep)) % cap if keep == cap else np.arange(keep)
        np.testing.assert_array_equal(s[slots], old["state"][-keep:].numpy())
        np.testing.assert_array_equal(s2[slots], old["next_state"][-keep:].numpy())
        if cap == capacity:
            np.testing.assert_array_equal(new._base_reward, ref._base_reward)
            ref_gen = ref.generator.get_state()
            _same_batch(new.sample(64), ref.sample(64))
            ref.generator.set_state(ref_gen)
        for t in range(2, 5):
            new.add(ep.states[t], ep.actions[t], float(ep.rewards[t]), ep.states[t + 1],
                    t == 4)
        e = new.end_episode()
        assert e.id == ref._next_episode_id
        np.testing.assert_array_equal(new.episode_states(e), ep.states[5 - e.length:5])
        assert new.end_episode().id == e.id + 1


def test_previous_format_with_non_stack_states_is_refused():
    ref = _FullStateReplay(10)
    rng = np.random.default_rng(0)
    for _ in range(3):
        ref.add(rng.normal(size=(3, 35)), np.zeros(4), 0.0, rng.normal(size=(3, 35)), False)
    with pytest.raises(ValueError, match="not a frame stack"):
        ReplayBuffer(10).load_state_dict(ref.state_dict())


def test_checkpoint_is_under_a_third_of_full_states():
    rng = np.random.default_rng(0)
    new, ref = ReplayBuffer(3000), _FullStateReplay(3000)
    _run([new, ref], rng, 3300, 2, max_steps=300)  # full and wrapped

    def nbytes(state) -> int:
        f = io.BytesIO()
        torch.save(state, f)
        return f.tell()

    assert nbytes(new.state_dict()) < nbytes(ref.state_dict()) / 3
