"""Experience collection: N envs stepped in turn, in the trainer's process or in its own.

``Collector`` is the pure part: it owns the envs, resets each with the next episode seed
when its episode ends, and turns one round (one step of every env) into ``Transition``
records. The actions are uniform random for the first ``start_steps`` env steps of the
run (abr-method.md) and the actor's plus exploration noise after (``act``).

``--sync`` (``policy.training.train``) drives a ``Collector`` in the trainer's own loop, so the
order of every random draw is fixed and a seed gives the same run. The parallel mode
runs ``collector_main`` in a second process (the learner keeps the main one):

- the learner publishes the actor's weights into a shared-memory tensor after every
  actor update (a seqlock: ``version`` is odd while it writes); the collector copies them
  in before a round when the version changed;
- the collector's lead is bounded: it does not start a round while its env steps past
  ``start_steps`` exceed the learner's updates by more than ``max_lead``. The learner never
  updates more often than once per env step received, so updates per env step stay 1 on
  average and drift by at most ``max_lead + envs`` steps;
- transitions go to the learner over a pipe, one message per round.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import torch

__all__ = ["Collector", "CollectorSpec", "SharedActor", "Transition", "collector_main"]

INFO_KEYS = ("goal_reached", "collision", "reward_components", "world")


class Transition(NamedTuple):
    """One env step of stream (env) ``stream``: (s_t, a_t, r_t, s_{t+1}) and how it ended."""

    stream: int
    state: np.ndarray
    action: np.ndarray
    reward: float
    next_state: np.ndarray
    terminated: bool
    truncated: bool
    info: dict[str, Any]  # goal_reached, collision, reward_components, world


class Collector:
    """Steps ``len(envs)`` envs in turn; env ``k`` is stream ``k``.

    Args:
        envs: objects with ``reset(seed=) -> (state, info)`` and ``step(a)`` as Gymnasium.
        episode_seed: episode index -> reset seed (episode ``i`` is the i-th reset).
        rng: draws the random actions and the exploration noise.
        next_episode: index of the next episode to reset (a resumed run's count).
        steps: env steps already taken in this run (decides the random phase).
    """

    def __init__(self, envs: list[Any], episode_seed: Callable[[int], int],
                 rng: np.random.Generator, max_action: float, action_dim: int,
                 start_steps: int, next_episode: int = 0, steps: int = 0) -> None:
        self.envs = envs
        self.episode_seed = episode_seed
        self.rng = rng
        self.max_action, self.action_dim = float(max_action), int(action_dim)
        self.start_steps = int(start_steps)
        self.next_episode, self.steps = int(next_episode), int(steps)
        self.states = [self._reset(k) for k in range(len(envs))]

    def _reset(self, k: int) -> np.ndarray:
        seed = self.episode_seed(self.next_episode)
        self.next_episode += 1
        return self.envs[k].reset(seed=seed)[0]

    def actions(self, act: Callable[[np.ndarray, np.random.Generator], np.ndarray]
                ) -> list[np.ndarray]:
        """One action per env: uniform in [-max_action, max_action] during the first
        ``start_steps`` steps, else ``act(states (N, ...), rng)`` (actor + noise)."""
        if self.steps < self.start_steps:
            return [self.rng.uniform(-self.max_action, self.max_action, self.action_dim)
                    .astype(np.float32) for _ in self.envs]
        stacked = np.stack(self.states)
        return list(np.asarray(act(stacked, self.rng)).reshape(len(self.envs), -1))

    def round(self, act: Callable[[np.ndarray, np.random.Generator], np.ndarray]
              ) -> list[Transition]:
        """Step every env once; an env whose episode ended is reset with the next seed."""
        out = []
        for k, action in enumerate(self.actions(act)):
            state = self.states[k]
            next_state, reward, terminated, truncated, info = self.envs[k].step(action)
            self.steps += 1
            out.append(Transition(k, state, action, float(reward), next_state,
                                  bool(terminated), bool(truncated),
                                  {key: info[key] for key in INFO_KEYS if key in info}))
            self.states[k] = self._reset(k) if terminated or truncated else next_state
        return out


class SharedActor:
    """The actor's parameters in one shared-memory float32 tensor, with a seqlock.

    ``publish`` (learner) and ``fetch`` (collector) copy all parameters at once; the reader
    retries while a write is in progress, so it never loads a half-written actor.
    """

    def __init__(self, actor: torch.nn.Module, ctx: Any) -> None:
        n = sum(p.numel() for p in actor.parameters())
        self.flat = torch.zeros(n, dtype=torch.float32).share_memory_()
        self.version = ctx.Value("q", 0, lock=False)
        self.updates = ctx.Value("q", 0, lock=False)  # learner's update count

    def publish(self, actor: torch.nn.Module) -> None:
        with torch.no_grad():
            vec = torch.nn.utils.parameters_to_vector([p.detach() for p in
                                                       actor.parameters()]).cpu()
            self.version.value += 1  # odd: writing
            self.flat.copy_(vec)
            self.version.value += 1  # even: done

    def fetch(self, actor: torch.nn.Module, seen: int) -> int:
        """Copy newer weights into ``actor``; returns the version now held."""
        while True:
            v = self.version.value
            if v == seen:
                return seen
            if v % 2:  # a write in progress
                time.sleep(0)
                continue
            with torch.no_grad():
                torch.nn.utils.vector_to_parameters(self.flat.clone(), actor.parameters())
            if self.version.value == v:
                return v


@dataclass
class CollectorSpec:
    """What the collector process needs to build its envs and actor (picklable)."""

    make_envs: Callable[[int], list[Any]]  # n -> envs
    envs: int
    actor_kwargs: dict[str, Any]
    exploration_noise: float
    seed: int
    max_action: float
    action_dim: int
    start_steps: int
    next_episode: int
    steps: int
    max_lead: int
    # the learner (built there): the collector checks it is still its parent once its
    # parent-death signal is set, since the learner may die while it starts
    learner_pid: int = field(default_factory=os.getpid)


def _die_with_parent() -> None:
    try:  # Linux: SIGKILL when the learner dies, however it dies
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def collector_main(conn: Any, spec: CollectorSpec, shared: SharedActor, stop: Any,
                   episode_seed: Callable[[int], int]) -> None:
    """The collector process: rounds of env steps sent to the learner until ``stop``."""
    _die_with_parent()
    parent = spec.learner_pid
    if os.getppid() != parent:  # the learner died before the death signal was set
        conn.close()
        return
    torch.set_num_threads(1)
    from policy.algorithms.networks import Actor
    from policy.algorithms.td3 import explore

    actor = Actor(**spec.actor_kwargs).requires_grad_(False)
    seen = shared.fetch(actor, -1)
    # a fresh run draws its random-action phase as --sync does (the trainer's generator,
    # seeded with the run's seed); a resumed one from a generator of its own
    rng = np.random.default_rng(spec.seed if spec.steps == 0 else [spec.seed, spec.steps])
    collector = Collector(spec.make_envs(spec.envs), episode_seed, rng, spec.max_action,
                          spec.action_dim, spec.start_steps, spec.next_episode, spec.steps)

    def act(states: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        with torch.no_grad():
            a = actor(torch.as_tensor(states, dtype=torch.float32).reshape(len(states), -1))
        return explore(a.numpy(), rng, spec.exploration_noise, spec.max_action)

    try:
        while not stop.is_set():
            while (collector.steps - spec.start_steps + 1 - shared.updates.value
                   > spec.max_lead):  # bounded lead on the learner
                if stop.is_set() or os.getppid() != parent:
                    return
                time.sleep(0.0002)
            seen = shared.fetch(actor, seen)
            conn.send(collector.round(act))
    except (BrokenPipeError, EOFError, ConnectionResetError, KeyboardInterrupt):
        pass
    finally:
        conn.close()
