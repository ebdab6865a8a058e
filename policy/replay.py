"""Experience replay for TD3/DDPG with per-episode index ranges (paper Algorithm 3.1).

Transitions ``(s_t, a_t, r_t, s_{t+1}, d_t)`` live in preallocated numpy arrays used as a
ring of ``capacity`` slots (1e6, Table 4.1). Besides the reward used for learning the
buffer keeps every transition's *base* reward (eq. 3.5 or the collision reward) so that a
goal-reward variant (TR, NGR, EGR, ABR; ``policy.rewards`` / ``policy.abr``) can rewrite
an episode's rewards from base when the episode ends, however often it is done.

``done`` is 1 only for a *terminal* transition (collision, goal). A time-limit
truncation (300 steps) ends the episode but is not terminal: the critic target still
bootstraps from ``s_{t+1}`` (eq. 2.12).

Each episode occupies a contiguous range of the ring, possibly wrapping past the end;
``Episode`` records its start slot and length, and a per-slot episode id detects an
episode whose slots were overwritten since. Sampling is uniform with a seeded
``torch.Generator``; ``sample`` returns torch tensors (views built once, no per-step
numpy->torch conversion).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch

__all__ = ["Batch", "Episode", "ReplayBuffer"]


class Batch(NamedTuple):
    """A mini-batch; states flattened to (B, frames * attributes) for the MLPs."""

    state: torch.Tensor  # (B, state_dim) float32
    action: torch.Tensor  # (B, action_dim) float32
    reward: torch.Tensor  # (B, 1) float32
    next_state: torch.Tensor  # (B, state_dim) float32
    done: torch.Tensor  # (B, 1) float32, 1 = terminal (not truncation)


@dataclass(frozen=True)
class Episode:
    """An episode's range in the ring: slots ``start, start+1, ...`` (mod capacity)."""

    id: int
    start: int
    length: int


class ReplayBuffer:
    """Ring buffer of transitions with episode bookkeeping.

    Args:
        capacity: number of transitions kept (paper: 1e6). Arrays are allocated once;
            untouched pages cost no memory.
        state_shape: shape of one state, (p_frames, attributes) = (3, 35).
        action_dim: 4 (l_x, l_y, l_z, a_z).
        seed: seed of the sampling generator.
    """

    def __init__(
        self,
        capacity: int = 1_000_000,
        state_shape: tuple[int, ...] = (3, 35),
        action_dim: int = 4,
        seed: int = 0,
    ) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self.capacity = int(capacity)
        self.state_shape = tuple(int(s) for s in state_shape)
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
        self._views()
        self.ptr = 0  # next slot to write
        self.size = 0  # filled slots
        self._next_episode_id = 0
        self._open_length = 0  # transitions of the episode in progress
        self.generator = torch.Generator().manual_seed(int(seed))

    def _views(self) -> None:
        # torch views sharing memory with the numpy arrays, so sampling stays in torch
        self._t = (
            torch.from_numpy(self._state),
            torch.from_numpy(self._action),
            torch.from_numpy(self._reward),
            torch.from_numpy(self._next_state),
            torch.from_numpy(self._done),
        )

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
    ) -> int:
        """Store one transition of the episode in progress; returns its slot.

        ``reward`` is the base reward (eq. 3.5, or the collision reward); it is also the
        learning reward until a goal-reward variant rewrites the episode. ``terminal`` is
        True only for collision/goal, never for a time-limit truncation.
        """
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

    @property
    def open_episode(self) -> Episode:
        """The episode in progress (its transitions so far)."""
        length = min(self._open_length, self.capacity)
        return Episode(self._next_episode_id, (self.ptr - length) % self.capacity, length)

    def end_episode(self) -> Episode:
        """Close the episode in progress and return its range.

        If the episode was longer than the buffer only its last ``capacity`` transitions
        survive, and the range covers those.
        """
        ep = self.open_episode
        self._next_episode_id += 1
        self._open_length = 0
        return ep

    # ------------------------------------------------------- episode rewriting

    def indices(self, episode: Episode) -> np.ndarray:
        """Slots of ``episode`` in episode order (handles the ring wrap-around).

        Raises KeyError if any of them has been overwritten by a later episode.
        """
        idx = (episode.start + np.arange(episode.length)) % self.capacity
        if episode.length and not np.all(self._episode_id[idx] == episode.id):
            raise KeyError(f"episode {episode.id} has been overwritten in the replay buffer")
        return idx

    def episode_base_rewards(self, episode: Episode) -> np.ndarray:
        return self._base_reward[self.indices(episode)].copy()

    def episode_rewards(self, episode: Episode) -> np.ndarray:
        return self._reward[self.indices(episode), 0].copy()

    def episode_states(self, episode: Episode) -> np.ndarray:
        """States s_1..s_T of the episode, shape (T, *state_shape)."""
        return self._state[self.indices(episode)].reshape(-1, *self.state_shape)

    def episode_dones(self, episode: Episode) -> np.ndarray:
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
        s, a, r, s2, d = self._t
        return Batch(s[idx], a[idx], r[idx], s2[idx], d[idx])

    # ------------------------------------------------------------- checkpoints

    def _chronological(self) -> np.ndarray:
        if self.size < self.capacity:
            return np.arange(self.size)
        return (self.ptr + np.arange(self.capacity)) % self.capacity

    def state_dict(self) -> dict[str, Any]:
        """The filled part only, oldest transition first (torch tensors, so it loads with
        ``torch.load(weights_only=True)``)."""
        idx = self._chronological()

        def take(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(a[idx])  # fancy indexing copies

        return {
            "state_shape": list(self.state_shape),
            "action_dim": self.action_dim,
            "state": take(self._state),
            "action": take(self._action),
            "reward": take(self._reward),
            "base_reward": take(self._base_reward),
            "next_state": take(self._next_state),
            "done": take(self._done),
            "episode_id": take(self._episode_id),
            "capacity": self.capacity,
            "ptr": self.ptr,
            "next_episode_id": self._next_episode_id,
            "open_length": self._open_length,
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a ``state_dict`` into this buffer (its capacity may differ; if smaller,
        the oldest transitions are dropped)."""
        shapes = (tuple(state["state_shape"]), int(state["action_dim"]))
        if shapes != (self.state_shape, self.action_dim):
            raise ValueError("replay state_dict has different state/action shapes")
        n = int(state["state"].shape[0])
        keep = min(n, self.capacity)
        src = slice(n - keep, n)
        # same capacity and full: restore the exact ring layout (so sampling replays);
        # otherwise oldest first from slot 0
        same_ring = n == self.capacity == int(state["capacity"])
        start = int(state["ptr"]) if same_ring else 0
        dst = (start + np.arange(keep)) % self.capacity
        self._episode_id[:] = -1
        for name in ("state", "action", "reward", "base_reward", "next_state", "done"):
            getattr(self, "_" + name)[dst] = state[name][src].numpy()
        self._episode_id[dst] = state["episode_id"][src].numpy()
        self.size = keep
        self.ptr = (start + keep) % self.capacity
        self._next_episode_id = int(state["next_episode_id"])
        self._open_length = min(int(state["open_length"]), keep)
        self.generator.set_state(state["generator"])
