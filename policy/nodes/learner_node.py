"""The learner node (``skyloop learner``): episodes from live runs -> TD3 -> actor weights.

Subscribes the log contract's topics (``episode``, ``observation``, ``truth``,
``cmd_vel``) of every vehicle (``skyloop/*/...``) or of a list. Zenoh callbacks only
enqueue (a full queue is a counted drop); the main loop feeds the
:class:`~policy.logs.episode_assembler.EpisodeAssembler`, turns each whole episode into
transitions with the code ``--from-logs`` uses (:mod:`policy.logs.transitions`), lets the
goal reward (TR/NGR/EGR/ABR) rewrite them in the replay buffer and runs TD3 (or DDPG)
updates: ``updates_per_step`` per new step once ``warmup`` transitions are in, done in
small chunks between queue drains; the first ``critic_warmup`` updates train the critic
only (a fresh critic would otherwise drag a trained initial actor around). Every
``publish_every`` consumed episodes, once the updates those episodes owed are done and
the actor has moved, it publishes the actor on ``skyloop/<vehicle>/actor`` for each
vehicle served, with a version counting up from 1
(``policy.nodes.weights``). A checkpoint (agent, replay buffer, goal-reward state, counters,
RNG states) is written atomically every ``checkpoint_every`` episodes and on exit;
``resume`` continues from it, versions included.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from bus import keys
from bus.task import TASK
from policy.algorithms.agents import make_agent, make_goal_reward
from policy.algorithms.replay import ReplayBuffer
from policy.algorithms.rewards import RewardConfig
from policy.algorithms.td3 import flush_denormals
from policy.logs.episode_assembler import TOPICS, AssemblerConfig, EpisodeAssembler
from policy.logs.transitions import add_episode, transitions_from_steps
from policy.nodes.learner import LearnerConfig
from policy.nodes.weights import actor_weights_message

log = logging.getLogger("skyloop.learner")
CHECKPOINT, ACTOR, SUMMARY = "checkpoint.pt", "actor.pt", "summary.json"
CHECKPOINT_FORMAT = "skyloop-learner-1"
PUBLISH_LINE = "SKYLOOP-LEARNER-PUBLISHED "
SUMMARY_LINE = "SKYLOOP-LEARNER-SUMMARY "
READY_LINE = "SKYLOOP-LEARNER-READY"  # subscribed, learning
UPDATE_CHUNK = 25  # updates between two drains of the queue


class Learner:
    """See the module docstring. ``emit`` gets the PUBLISH and SUMMARY lines."""

    def __init__(self, bus: Any, config: LearnerConfig, out: Path,
                 emit: Callable[[str], None] = print) -> None:
        config.validate()
        self.bus, self.config, self.out, self.emit = bus, config, Path(out), emit
        torch.set_num_threads(config.threads)
        torch.manual_seed(config.seed)
        self.agent = make_agent(config.algo, seed=config.seed)
        self.agent.task = TASK.to_dict()  # recorded in the actor files it publishes
        self.buffer = ReplayBuffer(config.buffer_size, TASK.state_shape, TASK.action_dim,
                                   seed=config.seed)
        self.reward_config = RewardConfig()
        self.goal_reward = make_goal_reward(config.reward, self.reward_config, seed=config.seed)
        self.assembler = EpisodeAssembler(AssemblerConfig(grace_s=config.grace_s))
        self.episodes = self.transitions = self.version = 0
        self.by_vehicle: dict[str, int] = {}
        self.owed = 0.0  # updates owed by the steps consumed
        self.publish_at: list[int] = []  # agent.updates at which to publish, in order
        self.since_publish = 0  # episodes consumed since the last publish
        self.updates_at_publish = 0
        self.inconsistent = 0
        self.queue_dropped = 0
        self._q: queue.Queue[tuple] = queue.Queue(maxsize=config.queue_size)
        self._lock = threading.Lock()
        self.publishers: dict[str, Any] = {}
        self.resumed = False
        if config.resume:
            self.load(self.out / CHECKPOINT)
        elif (self.out / CHECKPOINT).exists():
            raise FileExistsError(f"{self.out} already holds a learner run; use --resume "
                                  "or a new --out")
        elif config.init_actor not in (None, "scratch"):
            self._init_actor(config.init_actor)
        self.subscriptions = [
            bus.subscribe(topic, vehicle, lambda v, msg, t=topic: self._on_message(t, v, msg),
                          with_vehicle=True)
            for vehicle in config.vehicles for topic in TOPICS]
        for vehicle in config.vehicles:
            if vehicle != "*":
                self._publisher(vehicle)

    def _init_actor(self, init: str) -> None:
        from policy.algorithms.td3 import load_actor
        from policy.shipped import policy_path

        path = policy_path(init, flag="--init-actor")
        if not path.is_file():
            raise FileNotFoundError(f"--init-actor {path}: no such actor file")
        self.agent.actor.load_state_dict(load_actor(path, task=TASK).state_dict())
        self.agent.actor_target.load_state_dict(self.agent.actor.state_dict())
        log.info("actor initialised from %s", path)

    # ------------------------------------------------------------------ bus side
    def _on_message(self, topic: str, vehicle: str, msg: Any) -> None:  # Zenoh thread
        try:
            self._q.put_nowait((topic, vehicle, msg, time.monotonic()))
        except queue.Full:
            with self._lock:
                self.queue_dropped += 1

    def _publisher(self, vehicle: str) -> Any:
        if vehicle not in self.publishers:
            self.publishers[vehicle] = self.bus.publisher(keys.ACTOR, vehicle)
        return self.publishers[vehicle]

    def drain(self, timeout: float) -> int:
        """Feed every queued message to the assembler (waiting up to ``timeout`` for
        the first); returns how many."""
        n = 0
        try:
            item = self._q.get(timeout=timeout) if timeout > 0 else self._q.get_nowait()
            while True:
                topic, vehicle, msg, t = item
                if vehicle not in self.publishers and "*" in self.config.vehicles:
                    self._publisher(vehicle)
                self.assembler.add(vehicle, topic, msg, t)
                n += 1
                item = self._q.get_nowait()
        except queue.Empty:
            return n

    # ------------------------------------------------------------------ learning
    def consume(self, now: float) -> int:
        """Add the episodes that are whole to the replay buffer; returns how many."""
        n = 0
        for vehicle, index, steps in self.assembler.poll(now):
            try:
                tr = transitions_from_steps(steps, self.reward_config)
            except ValueError as exc:
                self.inconsistent += 1
                log.warning("%s episode %d skipped: %s", vehicle, index, exc)
                continue
            add_episode(tr, self.buffer, self.goal_reward)
            T = len(tr.actions)
            self.episodes += 1
            self.transitions += T
            self.by_vehicle[vehicle] = self.by_vehicle.get(vehicle, 0) + 1
            if len(self.buffer) >= self.config.warmup:
                self.owed += T * self.config.updates_per_step
            self.since_publish += 1
            if self.since_publish >= self.config.publish_every:
                self.since_publish = 0
                self.publish_at.append(self.agent.updates + int(self.owed))
            log.debug("%s episode %d: %d steps, %s", vehicle, index, T, steps.outcome)
            n += 1
        return n

    def consume_rest(self) -> int:
        """On stop: take in what is queued and whole (no more updates); how many."""
        self.drain(0.0)
        return self.consume(time.monotonic())

    def update(self, limit: int = UPDATE_CHUNK) -> int:
        """Run up to ``limit`` owed updates; returns how many ran."""
        n = min(int(self.owed), limit)
        batch = self.agent.config.batch_size
        with flush_denormals():  # Adam's moments of dead units: see policy.algorithms.td3
            for _ in range(n):
                self.agent.update(self.buffer.sample(batch),
                                  train_actor=self.agent.updates >= self.config.critic_warmup)
        self.owed -= n
        return n

    def maybe_publish(self) -> bool:
        if not self.publish_at or self.agent.updates < self.publish_at[0]:
            return False
        while self.publish_at and self.publish_at[0] <= self.agent.updates:
            self.publish_at.pop(0)  # a learner behind publishes once for every target met
        if self.agent.updates <= max(self.updates_at_publish, self.config.critic_warmup):
            return False  # the actor has not moved since the last publish
        self.version += 1
        self.updates_at_publish = self.agent.updates
        msg = actor_weights_message(self.agent, self.version, time.time())
        for pub in self.publishers.values():
            pub.put(msg)
        self.emit(PUBLISH_LINE + json.dumps(
            {"version": self.version, "episodes": self.episodes, "updates": self.agent.updates,
             "transitions": self.transitions, "vehicles": sorted(self.publishers)}))
        log.info("published actor version %d to %s (%d episodes, %d updates)", self.version,
                 sorted(self.publishers), self.episodes, self.agent.updates)
        return True

    # ------------------------------------------------------------------ the loop
    def run(self, stop: Callable[[], bool], progress: bool = True) -> dict:
        """Learn until ``stop()`` (or ``max_episodes`` consumed and their updates run)."""
        c = self.config
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "config.json").write_text(json.dumps(asdict(c), indent=2))
        t0, steps0, saved_at = time.monotonic(), self.transitions, self.episodes
        self.emit(READY_LINE)
        with tqdm(total=c.max_episodes or None, initial=self.episodes, unit="ep",
                  disable=not progress, desc=f"learner {c.algo}+{c.reward}",
                  file=sys.stderr) as bar:
            while not stop():
                self.drain(0.0 if self.owed >= 1 else 0.05)
                new = self.consume(time.monotonic())
                self.update()
                self.maybe_publish()
                if new:
                    bar.update(new)
                    rate = (self.transitions - steps0) / max(time.monotonic() - t0, 1e-9)
                    bar.set_postfix(upd=self.agent.updates, version=self.version,
                                    owed=int(self.owed), steps_s=f"{rate:.0f}",
                                    skipped=sum(self.skipped.values()), refresh=False)
                if self.episodes - saved_at >= c.checkpoint_every:
                    self.save()
                    saved_at = self.episodes
                if c.max_episodes and self.episodes >= c.max_episodes and self.owed < 1:
                    break
            bar.update(self.consume_rest())
        self.save()
        return self.summary(time.monotonic() - t0)

    @property
    def skipped(self) -> dict[str, int]:
        out = dict(self.assembler.skipped)
        if self.inconsistent:
            out["inconsistent"] = self.inconsistent
        with self._lock:
            if self.queue_dropped:
                out["queue full"] = self.queue_dropped
        undecodable = sum(s.counters()["decode_errors"] for s in self.subscriptions)
        if undecodable:
            out["undecodable payload"] = undecodable
        return out

    def summary(self, wall_s: float) -> dict:
        s = {"episodes": self.episodes, "by_vehicle": dict(self.by_vehicle),
             "transitions": self.transitions, "updates": self.agent.updates,
             "version": self.version, "skipped": self.skipped,
             "waiting": self.assembler.waiting, "owed": int(self.owed),
             "buffer": len(self.buffer), "wall_s": round(wall_s, 3),
             "algo": self.config.algo, "reward": self.config.reward,
             "resumed": self.resumed, "checkpoint": str(self.out / CHECKPOINT)}
        (self.out / SUMMARY).write_text(json.dumps(s, indent=2))
        self.emit(SUMMARY_LINE + json.dumps(s))
        return s

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        return {"format": CHECKPOINT_FORMAT, "config": asdict(self.config),
                "agent": self.agent.state_dict(), "buffer": self.buffer.state_dict(),
                "goal_reward": self.goal_reward.state_dict(),
                "torch_rng": torch.get_rng_state(), "episodes": self.episodes,
                "transitions": self.transitions, "version": self.version,
                "by_vehicle": dict(self.by_vehicle), "owed": self.owed,
                "updates_at_publish": self.updates_at_publish}

    def save(self) -> None:
        """Checkpoint and ``actor.pt`` (atomic: written aside, then renamed)."""
        self.out.mkdir(parents=True, exist_ok=True)
        tmp = self.out / (CHECKPOINT + ".tmp")
        torch.save(self.state_dict(), tmp)
        os.replace(tmp, self.out / CHECKPOINT)
        self.agent.save_actor(self.out / ACTOR)

    def load(self, path: Path) -> None:
        if not path.is_file():
            raise FileNotFoundError(f"{path}: nothing to resume")
        try:
            state = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as exc:  # noqa: BLE001 - torch raises many types
            raise ValueError(f"{path}: not a readable learner checkpoint ({exc})") from exc
        if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"{path}: not a skyloop learner checkpoint")
        for key in ("algo", "reward", "seed"):
            if state["config"][key] != getattr(self.config, key):
                raise ValueError(f"{path}: checkpoint has {key}={state['config'][key]!r} but "
                                 f"this run asks for {getattr(self.config, key)!r}")
        self.agent.load_state_dict(state["agent"])
        self.buffer.load_state_dict(state["buffer"])
        self.goal_reward.load_state_dict(state["goal_reward"])
        torch.set_rng_state(state["torch_rng"])
        self.episodes, self.transitions = state["episodes"], state["transitions"]
        self.version, self.owed = state["version"], float(state["owed"])
        self.by_vehicle = dict(state["by_vehicle"])
        self.updates_at_publish = state["updates_at_publish"]
        self.resumed = True
        log.info("resumed %s: %d episodes, %d updates, version %d", path, self.episodes,
                 self.agent.updates, self.version)
