"""Complete episodes from live bus messages, per vehicle (the learner's pure core).

Input: decoded messages of the log contract (:mod:`policy.transitions`) as they arrive,
``add(vehicle, topic, msg)``; output: :class:`~policy.transitions.EpisodeSteps` of every
episode that arrived whole, from :meth:`EpisodeAssembler.poll`. Nothing here blocks,
raises on bad input or touches a session: the learner calls it from its main loop.

Per vehicle: ``episode`` START opens an episode and END closes it; the ``truth`` poses
in between are its steps 0 .. T (one publisher with the events, so in order).
Observations are joined by their (episode, step) fields and body-frame ``cmd_vel`` by
stamp (the stamp of step k's truth), because they come from other processes
(perception, the bridge) and may arrive after the END event. A closed episode waits up
to ``grace_s`` for those; then it is emitted if whole, else skipped with a reason.

Skipped (counted in ``skipped`` by reason, never raised): an END without its START (the
learner joined mid-episode), a START without END (the next START came first), truth
poses or actions or observations missing after the grace, a message whose content does
not fit its type (``corrupt <topic>``; the step it carried is then missing too).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bus import keys
from bus import messages as m
from policy.transitions import EpisodeSteps, Pose

BODY_FRAME = "base_link"
TOPICS = (keys.EPISODE, keys.OBSERVATION, keys.TRUTH, keys.CMD_VEL)


@dataclass
class AssemblerConfig:
    grace_s: float = 2.0  # how long a closed episode waits for late observations/commands
    max_pending: int = 20_000  # observations / commands kept per vehicle (oldest dropped)
    obs_dim: int = 35


@dataclass
class _Open:
    index: int
    seed: int
    goal: np.ndarray
    stamps: list[int] = field(default_factory=list)
    truth: list[Pose] = field(default_factory=list)
    steps: int = 0
    outcome: str = ""
    deadline: float = 0.0


class _Vehicle:
    """What has arrived for one vehicle."""

    def __init__(self) -> None:
        self.open: _Open | None = None
        self.closed: list[_Open] = []
        self.observations: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self.commands: OrderedDict[int, tuple] = OrderedDict()


class EpisodeAssembler:
    """See the module docstring. ``complete`` counts emitted episodes, ``skipped``
    counts the others by reason, ``dropped`` counts observations/commands evicted
    because more than ``max_pending`` waited."""

    def __init__(self, config: AssemblerConfig | None = None) -> None:
        self.config = config or AssemblerConfig()
        self.vehicles: dict[str, _Vehicle] = {}
        self.complete = 0
        self.skipped: dict[str, int] = {}
        self.dropped = 0
        self.ignored = 0  # truth outside episodes, world-frame commands

    def skip(self, reason: str) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + 1

    # ------------------------------------------------------------------ input
    def add(self, vehicle: str, topic: str, msg: Any, now: float) -> None:
        """Take one decoded message of ``topic`` from ``vehicle`` (arrival time ``now``)."""
        v = self.vehicles.setdefault(vehicle, _Vehicle())
        try:
            if topic == keys.EPISODE:
                self._event(v, msg, now)
            elif topic == keys.TRUTH:
                pose = m.odometry_values(msg)
                if not all(np.all(np.isfinite(a)) for a in pose):
                    raise ValueError("non-finite pose")
                if v.open is None:
                    self.ignored += 1
                else:
                    v.open.stamps.append(m.nanoseconds(msg.header.stamp))
                    v.open.truth.append(pose)
            elif topic == keys.OBSERVATION:
                values = m.observation_values(msg)[-1]
                if values.shape != (self.config.obs_dim,) or not np.all(np.isfinite(values)):
                    raise ValueError(f"observation of shape {values.shape} or non-finite")
                self._put(v.observations, (int(msg.episode), int(msg.step)),
                          np.array(values, np.float32))
            elif topic == keys.CMD_VEL:
                if msg.header.frame_id != BODY_FRAME:
                    self.ignored += 1
                    return
                action = tuple(float(a) for a in m.twist_values(msg))
                if not np.all(np.isfinite(action)):
                    raise ValueError("non-finite command")
                self._put(v.commands, m.nanoseconds(msg.header.stamp), action)
            else:
                self.ignored += 1
        except (ValueError, TypeError, AttributeError, KeyError):
            self.skip(f"corrupt {topic}")

    def _put(self, table: OrderedDict, key: Any, value: Any) -> None:
        table[key] = value
        while len(table) > self.config.max_pending:
            table.popitem(last=False)
            self.dropped += 1

    def _event(self, v: _Vehicle, msg: Any, now: float) -> None:
        if msg.event == m.START:
            if v.open is not None:
                self.skip("START without END")
                self._forget(v, v.open)
            v.open = _Open(int(msg.episode), int(msg.seed),
                           np.array([msg.goal.x, msg.goal.y, msg.goal.z], np.float64))
        elif msg.event == m.END:
            ep, v.open = v.open, None
            if ep is None or ep.index != int(msg.episode):
                self.skip("END without START")
                return
            ep.steps, ep.outcome = int(msg.steps), m.outcome_name(msg)
            ep.deadline = now + self.config.grace_s
            v.closed.append(ep)
        else:
            raise ValueError(f"event {msg.event}")

    # ------------------------------------------------------------------ output
    def poll(self, now: float) -> list[tuple[str, int, EpisodeSteps]]:
        """Episodes that are whole now, as ``(vehicle, episode index, steps)``; closed
        episodes past their grace are skipped (counted) and forgotten."""
        out = []
        for name, v in self.vehicles.items():
            keep = []
            for ep in v.closed:
                done, reason = self._try(v, ep)
                if done is not None:
                    out.append((name, ep.index, done))
                    self.complete += 1
                elif reason is not None and (now >= ep.deadline or reason == "truth"):
                    self.skip(f"missing {reason}")
                else:
                    keep.append(ep)
                    continue
                self._forget(v, ep)
            v.closed = keep
        return out

    def _try(self, v: _Vehicle, ep: _Open) -> tuple[EpisodeSteps | None, str | None]:
        T = ep.steps
        if T < 1 or len(ep.truth) != T + 1:
            return None, "truth"
        actions = [v.commands.get(s) for s in ep.stamps[:T]]
        if any(a is None for a in actions):
            return None, "actions"
        obs = {k: v.observations.get((ep.index, k)) for k in range(T + 1)}
        if any(obs[k] is None for k in range(T)):
            return None, "observations"
        if obs[T] is None:
            del obs[T]
        return EpisodeSteps(ep.goal, T, ep.outcome, obs, ep.truth, actions), None

    def _forget(self, v: _Vehicle, ep: _Open) -> None:
        for key in [k for k in v.observations if k[0] == ep.index]:
            del v.observations[key]
        last = ep.stamps[-1] if ep.stamps else None
        if last is not None:
            for key in [k for k in v.commands if k <= last]:
                del v.commands[key]

    @property
    def waiting(self) -> int:
        """Closed episodes still waiting for late messages."""
        return sum(len(v.closed) for v in self.vehicles.values())
