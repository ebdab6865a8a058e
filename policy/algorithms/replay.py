"""Experience replay for TD3/DDPG with per-episode slot lists (paper Algorithm 3.1).

Transitions ``(s_t, a_t, r_t, s_{t+1}, d_t)`` live in preallocated numpy arrays used as a
ring of ``capacity`` slots (1e6, Table 4.1). Besides the reward used for learning the
buffer keeps every transition's *base* reward (eq. 3.5 or the collision reward) so that a
goal-reward variant (TR, NGR, EGR, ABR; ``policy.algorithms.rewards`` /
``policy.algorithms.abr``) can rewrite an episode's rewards from base when the episode
ends, however often it is done.

``done`` is 1 only for a *terminal* transition (collision, goal). A time-limit
truncation (300 steps) ends the episode but is not terminal: the critic target still
bootstraps from ``s_{t+1}`` (eq. 2.12).

Frame stacks, stored once
-------------------------
A state is the stack of the last ``p = state_shape[0]`` observations,
``s_t = (o_{t-p+1}, ..., o_t)``, zeros before the episode's first observation
(abr-method.md), and ``s_{t+1} = (o_{t-p+2}, ..., o_{t+1})``: consecutive states share
``p - 1`` frames and a transition adds one new frame, ``o_{t+1}``. So each frame is stored
once and the states are gathered by index:

- ``_frames`` (capacity * (1 + p), attributes) float32 is the frame pool. Row ``i <
  capacity`` is slot ``i``'s new frame ``o_{t+1}`` (the last row of its next_state).
  Above it sit *head blocks* of ``p`` rows: the whole state ``s_t`` of a slot that is the
  first stored transition of its episode (whatever it holds: zeros from the env,
  anything from logs). Blocks are reused through a free list, so only about as many as
  there are episodes in the buffer are ever touched (untouched pages cost no memory).
- ``_rows`` (2, capacity, p) int64: pool rows of ``s_t`` (``[0, i]``) and of ``s_{t+1}``
  (``[1, i]``). For a slot ``i`` with predecessor ``j`` (same episode, one step
  earlier): ``rows[0, i] = rows[1, j]`` and ``rows[1, i] = rows[1, j][1:] + [i]``; for a
  first slot with head block at row ``h``: ``rows[0, i] = h .. h+p-1`` and
  ``rows[1, i] = h+1 .. h+p-1, i``.
- ``_prev`` / ``_next`` (capacity,) int64: the neighbouring slots of the same episode
  (-1: none), ``_head`` (capacity,): a first slot's head block row (-1 otherwise).

``sample`` is two ``index_select`` calls: the batch's (2, B, p) pool rows, then those
frames, viewed as (2, B, p * attributes) -> state, next_state. The values are exactly the
stacks that were added (same generator draws, same float32 bits), so a seeded run's
batches are the same as with full stored states.

``add`` checks that ``state`` / ``next_state`` are a frame stack continuing the stream's
episode: ``next_state[:-1] == state[1:]`` and, after an episode's first transition,
``state ==`` the previous ``next_state`` (bitwise); otherwise ``ValueError``.

Overwrite (ring wrap-around): the slot overwritten is always the oldest one, hence the
first stored transition of its episode. Its successor (if any) becomes the episode's
first: it takes over the head block, filled with its own state (the overwritten slot's
next_state, gathered before it is lost), and the pool rows of it and its next ``p - 1``
successors are rewritten. Every stored transition stays exact; nothing is resampled.

Episodes and streams: ``add``, ``end_episode`` and ``open_episode`` take ``stream`` (which
env; several episodes can be open at once and interleave in the ring). ``Episode`` holds
its slots in episode order; a per-slot episode id detects an episode whose slots were
overwritten since. The stored transitions of an episode are always a suffix of it.

Checkpoints (``state_dict``) hold the compact form, oldest transition first: per
transition the new frame, action, rewards, done, episode id and the index of its
predecessor, plus the whole state of each first transition. Measured with 300-step
episodes of (3, 35) states (``torch.save`` to memory; previous = full state and
next_state per transition, a format that still loads):

============  ==============  ==============  =====
transitions   previous        compact         ratio
============  ==============  ==============  =====
100,000       87.6 MB         18.5 MB         0.21
1,000,000     876.0 MB        185.4 MB        0.21
============  ==============  ==============  =====

``sample(100)`` (one thread, median, two cores busy with other work): 10,000 slots
75 -> 29 us, 100,000 slots 123 -> 59 us, 1e6 slots 156 -> 76 us (two ``index_select``
over a 4x smaller pool instead of five advanced-indexing gathers). ``add`` costs about
the same (~6 us) until the ring is full, then ~10 us more for the overwrite bookkeeping.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import torch

from bus.task import TASK

__all__ = ["Batch", "Episode", "ReplayBuffer"]

FORMAT = "skyloop-replay-2"  # the compact checkpoint; format 1 had no "format" key


class Batch(NamedTuple):
    """A mini-batch; states flattened to (B, frames * attributes) for the MLPs."""

    state: torch.Tensor  # (B, state_dim) float32
    action: torch.Tensor  # (B, action_dim) float32
    reward: torch.Tensor  # (B, 1) float32
    next_state: torch.Tensor  # (B, state_dim) float32
    done: torch.Tensor  # (B, 1) float32, 1 = terminal (not truncation)


@dataclass(frozen=True, eq=False)
class Episode:
    """An episode's stored transitions: ring slots in episode order (read-only array)."""

    id: int
    slots: np.ndarray

    @property
    def length(self) -> int:
        return int(self.slots.shape[0])


@dataclass
class _Stream:
    """The open episode of one stream (env)."""

    id: int
    slots: deque[int] = field(default_factory=deque)  # stored ones, episode order
    last: int = -1  # slot of the latest transition (-1: none)
    stack: bytes | None = None  # latest next_state (float32 bytes): the next state


def _bits(a: np.ndarray) -> np.ndarray:
    return a.view(np.uint32)  # bitwise comparison: -0.0 != 0.0, NaN == same NaN


def _stack_rows(c: np.ndarray, prev: np.ndarray, head: np.ndarray, frames: int) -> np.ndarray:
    """Pool rows of the ``frames + 1`` frames ``(s_t, last frame of s_{t+1})`` of
    transitions ``c``, shape (len(c), frames + 1).

    The new frame of transition ``i`` is pool row ``i``; ``prev[i]`` is its predecessor
    (-1 for a first transition) and ``head[i]`` the row of a first transition's state
    frame 0 (its ``frames`` rows are consecutive). Walks back up to ``frames`` steps:
    with ``k`` predecessors, column ``j`` is frame ``k + j`` of the episode's frame
    sequence (head frames, then one new frame per transition).
    """
    chain = np.empty((frames + 1, c.shape[0]), np.int64)
    chain[0] = cur = c
    depth = np.zeros(c.shape[0], np.int64)
    for step in range(1, frames + 1):
        p = prev[cur]
        back = p >= 0
        cur = np.where(back, p, cur)
        depth += back
        chain[step] = cur
    j = np.arange(frames + 1)
    from_obs = depth[:, None] + j >= frames
    obs_rows = chain[frames - j].T
    head_rows = head[cur][:, None] + depth[:, None] + j  # cur is the first when depth < p
    return np.where(from_obs, obs_rows, head_rows)


class ReplayBuffer:
    """Ring buffer of transitions with episode bookkeeping (layout: module docstring).

    Args:
        capacity: number of transitions kept (paper: 1e6). Arrays are allocated once;
            untouched pages cost no memory.
        state_shape: shape of one state, (p_frames, attributes) = (3, 35); a 1-D shape
            is one frame.
        action_dim: numbers per action (the UAV task's 4: l_x, l_y, l_z, a_z).
        seed: seed of the sampling generator.
    """

    def __init__(
        self,
        capacity: int = 1_000_000,
        state_shape: tuple[int, ...] = TASK.state_shape,
        action_dim: int = TASK.action_dim,
        seed: int = 0,
    ) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self.capacity = int(capacity)
        self.state_shape = tuple(int(s) for s in state_shape)
        self.state_dim = int(np.prod(self.state_shape))
        self.action_dim = int(action_dim)
        self._p = self.state_shape[0] if len(self.state_shape) > 1 else 1  # frames
        self._attrs = self.state_dim // self._p
        n, p = self.capacity, self._p
        self._frames = np.zeros((n * (1 + p), self._attrs), np.float32)
        self._rows = np.zeros((2, n, p), np.int64)
        self._prev = np.full(n, -1, np.int64)
        self._next = np.full(n, -1, np.int64)
        self._head = np.full(n, -1, np.int64)
        self._action = np.zeros((n, self.action_dim), np.float32)
        self._reward = np.zeros((n, 1), np.float32)
        self._base_reward = np.zeros(n, np.float32)
        self._done = np.zeros((n, 1), np.float32)
        self._episode_id = np.full(n, -1, np.int64)
        self._head_range = np.arange(p)  # offsets of a head block's rows
        # torch views sharing memory with the numpy arrays, so sampling stays in torch
        self._t = tuple(
            torch.from_numpy(a)
            for a in (self._frames, self._rows, self._action, self._reward, self._done)
        )
        self.ptr = 0  # next slot to write
        self.size = 0  # filled slots
        self._reset_bookkeeping()
        self.generator = torch.Generator().manual_seed(int(seed))

    def _reset_bookkeeping(self) -> None:
        self._blocks_used = 0  # head blocks ever handed out
        self._free_heads: list[int] = []  # pool rows of released head blocks
        self._next_episode_id = 0
        self._streams: dict[int, _Stream] = {}
        self._open_by_id: dict[int, _Stream] = {}

    def __len__(self) -> int:
        return self.size

    # ------------------------------------------------------------------ writing

    def add(
        self,
        state: np.ndarray,
        action: np.ndarray,
        reward: float,
        next_state: np.ndarray,
        terminal: bool,
        *,
        stream: int = 0,
    ) -> int:
        """Store one transition of ``stream``'s open episode; returns its slot.

        ``reward`` is the base reward (eq. 3.5, or the collision reward); it is also the
        learning reward until a goal-reward variant rewrites the episode. ``terminal`` is
        True only for collision/goal, never for a time-limit truncation. ``state`` and
        ``next_state`` must be frame stacks continuing the episode (module docstring);
        an episode's first ``state`` may be anything.
        """
        p, width = self._p, self._attrs * 4  # bytes of one float32 frame
        s = np.asarray(state, np.float32)
        s2 = np.asarray(next_state, np.float32)
        if s.size != self.state_dim or s2.size != self.state_dim:
            raise ValueError(
                f"replay add: state and next_state must have {self.state_dim} "
                f"values {self.state_shape}, got {s.shape} and {s2.shape}"
            )
        s, s2 = s.reshape(p, self._attrs), s2.reshape(p, self._attrs)
        a = np.broadcast_to(np.asarray(action, np.float32).reshape(-1), (self.action_dim,))
        r = float(reward)  # inputs checked before anything is written
        st = self._streams.get(stream)
        s_bytes = s.tobytes()
        if st is not None and st.stack is not None and s_bytes != st.stack:
            raise ValueError(
                f"replay add (stream {stream}): state is not the previous "
                f"next_state of open episode {st.id} (frames must continue)"
            )
        if s2[:-1].tobytes() != s_bytes[width:]:
            raise ValueError(
                f"replay add (stream {stream}): next_state[:-1] != state[1:] "
                "(not a frame stack shifted by one observation)"
            )
        st = st or self._stream(stream)
        i = self.ptr
        if self.size == self.capacity:
            self._evict(i)
        last = st.last
        if last >= 0 and self._episode_id[last] == st.id:  # predecessor still stored
            self._write_rows(i, last)
            self._prev[i], self._next[last] = last, i
        else:
            h = self._alloc_head()
            self._frames[h : h + p] = s
            self._head[i] = h
            self._write_rows(i, -1)
            self._prev[i] = -1
        self._next[i] = -1
        self._frames[i] = s2[-1]
        self._action[i] = a
        self._reward[i, 0] = r
        self._base_reward[i] = r
        self._done[i, 0] = 1.0 if terminal else 0.0
        self._episode_id[i] = st.id
        self.ptr = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        st.slots.append(i)
        st.last, st.stack = i, s2.tobytes()
        return i

    def _stream(self, stream: int) -> _Stream:
        """``stream``'s open episode, opened (new id) if it has none."""
        st = self._streams.get(stream)
        if st is None:
            st = _Stream(self._next_episode_id)
            self._next_episode_id += 1
            self._streams[stream] = self._open_by_id[st.id] = st
        return st

    def _write_rows(self, i: int, pred: int) -> None:
        """Pool rows of slot ``i`` from its predecessor ``pred``, or (``pred`` = -1) from
        its head block at ``_head[i]``."""
        rows = self._rows
        if pred >= 0:
            rows[0, i] = rows[1, pred]
            rows[1, i, :-1] = rows[1, pred, 1:]
        else:
            own = self._head[i] + self._head_range
            rows[0, i] = own
            rows[1, i, :-1] = own[1:]
        rows[1, i, -1] = i

    def _alloc_head(self) -> int:
        if self._free_heads:
            return self._free_heads.pop()
        h = self.capacity + self._blocks_used * self._p
        self._blocks_used += 1
        return h

    def _evict(self, j: int) -> None:
        """Slot ``j`` (the oldest, so the first stored transition of its episode) is about
        to be overwritten: its successor becomes the episode's first transition."""
        h = int(self._head[j])
        if h < 0:  # an invariant, not an input error
            raise RuntimeError(f"replay: oldest slot {j} is not an episode's first")
        succ = int(self._next[j])
        if succ >= 0:  # successor's state = j's next_state, gathered before j is lost
            self._frames[h : h + self._p] = self._frames[self._rows[1, j]]
            self._head[succ], self._prev[succ] = h, -1
            self._write_rows(succ, -1)
            c, pred = int(self._next[succ]), succ
            for _ in range(self._p - 1):  # the next p-1 successors read head frames too
                if c < 0:
                    break
                self._write_rows(c, pred)
                c, pred = int(self._next[c]), c
        else:
            self._free_heads.append(h)
        self._head[j] = -1
        st = self._open_by_id.get(int(self._episode_id[j]))
        if st is not None:  # j is the front of that open episode's stored slots
            st.slots.popleft()
            if st.last == j:
                st.last = -1
        self._episode_id[j] = -1
        self._next[j] = -1

    def open_streams(self) -> list[int]:
        """The streams with an episode in progress (opened by ``add`` or ``open_episode``
        and not yet ended), in the order they were opened."""
        return list(self._streams)

    def open_episode(self, stream: int = 0) -> Episode:
        """``stream``'s episode in progress (its stored transitions so far)."""
        st = self._stream(stream)
        return self._episode(st)

    def end_episode(self, stream: int = 0) -> Episode:
        """Close ``stream``'s episode in progress and return it.

        If the episode was longer than the buffer only its last ``capacity`` transitions
        survive, and the episode covers those.
        """
        st = self._stream(stream)
        del self._streams[stream], self._open_by_id[st.id]
        return self._episode(st)

    @staticmethod
    def _episode(st: _Stream) -> Episode:
        slots = np.fromiter(st.slots, np.int64, len(st.slots))
        slots.setflags(write=False)
        return Episode(st.id, slots)

    # ------------------------------------------------------- episode rewriting

    def indices(self, episode: Episode) -> np.ndarray:
        """Slots of ``episode`` in episode order.

        Raises KeyError if any of them has been overwritten by a later episode.
        """
        idx = episode.slots
        if idx.shape[0] and not np.all(self._episode_id[idx] == episode.id):
            raise KeyError(f"episode {episode.id} has been overwritten in the replay buffer")
        return idx

    def episode_base_rewards(self, episode: Episode) -> np.ndarray:
        return self._base_reward[self.indices(episode)].copy()

    def stored_rewards(self, episode: Episode) -> np.ndarray:
        """The rewards the episode's transitions hold now (after its goal reward)."""
        return self._reward[self.indices(episode), 0].copy()

    def episode_states(self, episode: Episode) -> np.ndarray:
        """States s_1..s_T of the episode, shape (T, *state_shape)."""
        rows = self._rows[0, self.indices(episode)]
        return self._frames[rows].reshape(-1, *self.state_shape)

    def stored_dones(self, episode: Episode) -> np.ndarray:
        """The episode's terminal flags d_i as stored."""
        return self._done[self.indices(episode), 0].copy()

    def set_episode_rewards(self, episode: Episode, rewards: np.ndarray) -> None:
        idx = self.indices(episode)
        rewards = np.asarray(rewards, dtype=np.float32).reshape(-1)
        if rewards.shape[0] != idx.shape[0]:
            raise ValueError(f"{rewards.shape[0]} rewards for an episode of {idx.shape[0]}")
        self._reward[idx, 0] = rewards

    # ------------------------------------------------------------------ sampling

    def sample(self, batch_size: int) -> Batch:
        """Uniformly sample ``batch_size`` transitions (with replacement)."""
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        idx = torch.randint(self.size, (batch_size,), generator=self.generator)
        frames, rows, a, r, d = self._t
        both = frames.index_select(0, rows.index_select(1, idx).view(-1))
        both = both.view(2, batch_size, self.state_dim)
        return Batch(
            both[0], a.index_select(0, idx), r.index_select(0, idx), both[1], d.index_select(0, idx)
        )

    # ------------------------------------------------------------- checkpoints

    def _chronological(self) -> np.ndarray:
        if self.size < self.capacity:
            return np.arange(self.size)
        return (self.ptr + np.arange(self.capacity)) % self.capacity

    def state_dict(self) -> dict[str, Any]:
        """The filled part only, oldest transition first, in the compact form (module
        docstring); torch tensors, so it loads with ``torch.load(weights_only=True)``.

        ``prev`` is the index (in this dict) of each transition's predecessor, -1 for an
        episode's first stored transition, whose whole state is in ``first_state``.
        """
        idx = self._chronological()
        pos = np.empty(self.capacity, np.int64)
        pos[idx] = np.arange(idx.shape[0])
        prev = self._prev[idx]
        prev = np.where(prev >= 0, pos[np.maximum(prev, 0)], -1)
        firsts = idx[prev < 0]
        first_state = self._frames[self._rows[0, firsts]]
        keys = list(self._streams)
        streams = [self._streams[k] for k in keys]
        zeros = bytes(4 * self.state_dim)
        stacks = np.frombuffer(b"".join(s.stack or zeros for s in streams), np.float32).copy()

        def take(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(a[idx])  # fancy indexing copies

        return {
            "format": FORMAT,
            "state_shape": list(self.state_shape),
            "action_dim": self.action_dim,
            "obs": take(self._frames[: self.capacity]),
            "action": take(self._action),
            "reward": take(self._reward),
            "base_reward": take(self._base_reward),
            "done": take(self._done),
            "episode_id": take(self._episode_id),
            "prev": torch.from_numpy(prev),
            "first_state": torch.from_numpy(first_state),
            "stream": torch.tensor(keys, dtype=torch.int64),
            "stream_episode": torch.tensor([s.id for s in streams], dtype=torch.int64),
            "stream_stack": torch.from_numpy(stacks.reshape(len(streams), self._p, self._attrs)),
            "stream_has_stack": torch.tensor([s.stack is not None for s in streams]),
            "capacity": self.capacity,
            "ptr": self.ptr,
            "next_episode_id": self._next_episode_id,
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a ``state_dict`` into this buffer (its capacity may differ; if smaller,
        the oldest transitions are dropped, and a transition whose predecessor is dropped
        keeps its whole state). A previous-format dict (full ``state``/``next_state``) is
        converted."""
        shapes = (tuple(state["state_shape"]), int(state["action_dim"]))
        if shapes != (self.state_shape, self.action_dim):
            raise ValueError("replay state_dict has different state/action shapes")
        if "next_state" in state:
            state = self._from_full_states(state)
        elif state.get("format") != FORMAT:
            raise ValueError(f"unknown replay state_dict format {state.get('format')!r}")
        p, attrs, n = self._p, self._attrs, self.capacity
        obs = state["obs"].numpy()
        prev = state["prev"].numpy()
        m = int(obs.shape[0])
        keep = min(m, n)
        lo = m - keep
        # whole states of the kept transitions that start the buffer's part of an episode
        first = np.flatnonzero(prev < 0)
        head = np.full(m, -1, np.int64)
        head[first] = m + p * np.arange(first.shape[0])
        pool = np.concatenate([obs, state["first_state"].numpy().reshape(-1, attrs)])
        kept = np.arange(lo, m)
        starts = kept[prev[kept] < lo]
        start_states = pool[_stack_rows(starts, prev, head, p)[:, :p]]
        # same capacity and full: restore the exact ring layout (so sampling replays);
        # otherwise oldest first from slot 0
        same_ring = m == n == int(state["capacity"])
        begin = int(state["ptr"]) if same_ring else 0
        dst = (begin + kept - lo) % n
        self._reset_bookkeeping()
        for a in (self._prev, self._next, self._head, self._episode_id):
            a[:] = -1
        self._frames[dst] = obs[lo:]
        for name in ("action", "reward", "base_reward", "done", "episode_id"):
            getattr(self, "_" + name)[dst] = state[name][lo:].numpy()
        pred = np.where(prev[kept] >= lo, dst[np.maximum(prev[kept] - lo, 0)], -1)
        self._prev[dst] = pred
        self._next[pred[pred >= 0]] = dst[pred >= 0]
        self._blocks_used = starts.shape[0]
        self._frames[n : n + p * starts.shape[0]] = start_states.reshape(-1, attrs)
        self._head[dst[starts - lo]] = n + p * np.arange(starts.shape[0])
        rows = _stack_rows(dst, self._prev, self._head, p)
        self._rows[0, dst], self._rows[1, dst] = rows[:, :p], rows[:, 1:]
        self.size = keep
        self.ptr = (begin + keep) % n
        self._next_episode_id = int(state["next_episode_id"])
        eids = self._episode_id[dst]
        stacks = state["stream_stack"].numpy()
        has_stack = state["stream_has_stack"].numpy()
        for k, (key, eid) in enumerate(
            zip(state["stream"].tolist(), state["stream_episode"].tolist(), strict=True)
        ):
            slots = dst[eids == eid].tolist()
            st = _Stream(
                eid,
                deque(slots),
                slots[-1] if slots else -1,
                stacks[k].tobytes() if has_stack[k] else None,
            )
            self._streams[key] = self._open_by_id[eid] = st
        self.generator.set_state(state["generator"])

    def _from_full_states(self, state: dict[str, Any]) -> dict[str, Any]:
        """A previous-format dict (full states; one open episode, stream 0) in the
        compact form. A transition links to the one before it when both are of the same
        episode and its state is that one's next_state; otherwise it keeps its state."""
        p, attrs = self._p, self._attrs
        s = state["state"].numpy().reshape(-1, p, attrs)
        s2 = state["next_state"].numpy().reshape(-1, p, attrs)
        eid = state["episode_id"].numpy()
        m = s.shape[0]
        shifted = (_bits(s2[:, :-1]) == _bits(s[:, 1:])).all(axis=(1, 2))
        if not shifted.all():
            bad = int(np.flatnonzero(~shifted)[0])
            raise ValueError(
                f"replay state_dict: transition {bad} (oldest = 0) is not a "
                "frame stack (next_state[:-1] != state[1:]); cannot convert"
            )
        link = np.zeros(m, bool)
        link[1:] = (eid[1:] == eid[:-1]) & (_bits(s[1:]) == _bits(s2[:-1])).all(axis=(1, 2))
        next_id = int(state["next_episode_id"])
        is_open = int(state["open_length"]) > 0 and m > 0 and int(eid[-1]) == next_id
        return {
            **{
                k: state[k]
                for k in (
                    "action",
                    "reward",
                    "base_reward",
                    "done",
                    "episode_id",
                    "capacity",
                    "ptr",
                    "generator",
                )
            },
            "obs": torch.from_numpy(np.ascontiguousarray(s2[:, -1])),
            "prev": torch.from_numpy(np.where(link, np.arange(m) - 1, -1)),
            "first_state": torch.from_numpy(s[~link]),
            "stream": torch.tensor([0] if is_open else [], dtype=torch.int64),
            "stream_episode": torch.tensor([next_id] if is_open else [], dtype=torch.int64),
            "stream_stack": torch.from_numpy(s2[-1:] if is_open else s2[:0]),
            "stream_has_stack": torch.tensor([True] if is_open else [], dtype=torch.bool),
            "next_episode_id": next_id + 1 if is_open else next_id,
        }
