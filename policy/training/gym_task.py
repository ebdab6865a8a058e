"""Any Gymnasium env as a skyloop training task (the paper's second task, section 4).

The paper tests ABR on ``BipedalWalkerHardcore-v3``, a task without a goal point, by
treating "a certain episodic reward" as the goal. This wrapper gives any Gymnasium env
with a flat ``Box`` observation and ``Box`` action the interface the trainer uses for
the UAV env (``policy.training.env.UavNavEnv``):

- States are the last ``frames`` observations stacked FIFO, zeros before the first
  (Algorithm 3.1's ``s(0, 0, ..., o)``), shape ``(frames, obs_dim)``; ABR's feature CNN
  reads them with ``p_attributes = obs_dim``.
- The base reward is the env's own reward.
- ``info["goal_reached"]`` is True on the last step of an episode whose return reached
  ``goal_return`` **[choice: a documented grid parameter, abr-method.md]**, whether it
  ended by termination or by the env's time limit. ``info["collision"]`` is True on a
  termination that did not reach it (for the walker: a fall).

Actions are the agent's, clipped to the env's bounds; the bounds must be symmetric
(``-high == low``) since the agents act in ``[-max_action, max_action]``.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np

__all__ = ["GymTask", "check_env_id"]


def check_env_id(env_id: str) -> None:
    """Raise ``ValueError`` naming ``env_id`` if Gymnasium does not know it."""
    try:
        gymnasium.spec(env_id)
    except gymnasium.error.Error as exc:
        raise ValueError(f"unknown Gymnasium env id {env_id!r} ({exc})") from exc


class GymTask:
    """A Gymnasium env with stacked frames and a return threshold that counts as the goal."""

    def __init__(self, env_id: str, goal_return: float, frames: int = 3) -> None:
        check_env_id(env_id)
        self.env = gymnasium.make(env_id)
        obs_space, act_space = self.env.observation_space, self.env.action_space
        if not (isinstance(obs_space, gymnasium.spaces.Box) and len(obs_space.shape) == 1):
            raise ValueError(f"{env_id}: observation space must be a flat Box, got {obs_space}")
        if not isinstance(act_space, gymnasium.spaces.Box) or len(act_space.shape) != 1:
            raise ValueError(f"{env_id}: action space must be a flat Box, got {act_space}")
        if not np.allclose(act_space.low, -act_space.high):
            raise ValueError(f"{env_id}: action bounds must be symmetric, got {act_space}")
        self.frames = int(frames)
        self.obs_dim = int(obs_space.shape[0])
        self.action_dim = int(act_space.shape[0])
        self.max_action = float(np.max(act_space.high))
        self.goal_return = float(goal_return)
        self._stack = np.zeros((self.frames, self.obs_dim), np.float32)
        self._return = 0.0

    @property
    def state_shape(self) -> tuple[int, int]:
        return (self.frames, self.obs_dim)

    def _push(self, obs: np.ndarray) -> np.ndarray:
        self._stack[:-1] = self._stack[1:]
        self._stack[-1] = np.asarray(obs, np.float32)
        return self._stack.copy()

    def reset(self, seed: int | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed)
        self._stack[:] = 0.0
        self._return = 0.0
        return self._push(obs), info

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        action = np.clip(np.asarray(action, np.float32), -self.max_action, self.max_action)
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._return += float(reward)
        done = bool(terminated or truncated)
        reached = done and self._return >= self.goal_return
        info = dict(info, goal_reached=reached, collision=bool(terminated and not reached))
        return self._push(obs), float(reward), bool(terminated), bool(truncated), info

    def close(self) -> None:
        self.env.close()
