"""Complete episodes from live bus messages, per vehicle (the learner's pure core).

Input: decoded messages of the log contract (:mod:`policy.logs.transitions`) as they arrive,
``add(vehicle, topic, msg)``; output: :class:`~policy.logs.transitions.EpisodeSteps` of every
episode that arrived whole, from :meth:`EpisodeAssembler.poll`. Nothing here blocks,
raises on bad input or touches a session: the learner calls it from its main loop.

Per vehicle: ``episode`` START opens an episode and END closes it (one subscription,
so they arrive in order). Everything else is joined by key, because Zenoh delivers each
subscription on its own and other processes publish some of it (perception, the
bridge): the ``truth`` poses by stamp (every message of a step carries the step's stack
time; START carries step 0's and END step T's, so steps 0 .. T are the T + 1 truth
stamps from START's to END's; an episode's last stamp is also the next one's first,
so a stamp can hold two poses, in arrival order), body-frame ``cmd_vel`` by the stamp of
its step, and observations and step records by their (episode, step) fields. A closed
episode waits up to ``grace_s`` for messages still in flight; then it is emitted if whole,
else skipped with a reason. Step records (the sim's ``step_record``, steps 1 .. T) are
part of a whole episode once the vehicle has sent one (a sim that publishes them); from a
vehicle that never has, episodes come without them and their rewards are recomputed
(:mod:`policy.logs.transitions`).

Skipped (counted in ``skipped`` by reason, never raised): an END without its START (the
learner joined mid-episode), a START without END (the next START came first), truth
poses or actions or observations missing after the grace, a message whose content does
not fit its type (``corrupt <topic>``; the step it carried is then missing too).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np

from bus import keys
from bus import messages as m
from bus.task import TASK, StepRecord
from policy.logs.transitions import EpisodeSteps, Pose

TOPICS = (keys.EPISODE, keys.OBSERVATION, keys.TRUTH, keys.CMD_VEL, keys.STEP_RECORD)


@dataclass
class AssemblerConfig:
    grace_s: float = 2.0  # how long a closed episode waits for late observations/commands
    max_pending: int = 20_000  # observations / commands kept per vehicle (oldest dropped)
    obs_dim: int = TASK.obs_dim


@dataclass
class _Open:
    index: int
    seed: int
    goal: np.ndarray
    start_stamp: int
    shared_start: bool  # the previous episode ended at start_stamp: its pose is first
    limits: dict | None = None  # the episode limits START records
    end_stamp: int = 0
    steps: int = 0
    outcome: str = ""
    deadline: float = 0.0


class _Vehicle:
    """What has arrived for one vehicle."""

    def __init__(self) -> None:
        self.open: _Open | None = None
        self.closed: list[_Open] = []
        self.observations: OrderedDict[tuple[int, int], tuple[np.ndarray, dict | None]] = \
            OrderedDict()
        self.commands: OrderedDict[int, tuple] = OrderedDict()
        self.truth: OrderedDict[int, list[Pose]] = OrderedDict()
        self.records: OrderedDict[tuple[int, int], StepRecord] = OrderedDict()
        self.sends_records = False  # a step record has come from this vehicle
        self.last_end_stamp: int | None = None


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
        self.ignored = 0  # world-frame commands, unknown topics

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
                stamp = m.nanoseconds(msg.header.stamp)
                self._put(v.truth, stamp, v.truth.pop(stamp, []) + [pose])
            elif topic == keys.OBSERVATION:
                values = m.observation_values(msg)[-1]
                if values.shape != (self.config.obs_dim,) or not np.all(np.isfinite(values)):
                    raise ValueError(f"observation of shape {values.shape} or non-finite")
                self._put(v.observations, (int(msg.episode), int(msg.step)),
                          (np.array(values, np.float32), m.observation_scaling(msg)))
            elif topic == keys.CMD_VEL:
                if not m.is_action(msg):
                    self.ignored += 1
                    return
                action = tuple(float(a) for a in m.setpoint_values(msg))
                if not np.all(np.isfinite(action)):
                    raise ValueError("non-finite command")
                self._put(v.commands, m.nanoseconds(msg.header.stamp), action)
            elif topic == keys.STEP_RECORD:
                record = m.step_record_values(msg)
                self._put(v.records, (record.episode, record.step), record)
                v.sends_records = True
            else:
                self.ignored += 1
        except (ValueError, TypeError, AttributeError, KeyError):
            self.skip(f"corrupt {topic}")

    def _put(self, table: OrderedDict, key: Any, value: Any) -> None:
        table[key] = value
        table.move_to_end(key)
        while len(table) > self.config.max_pending:
            table.popitem(last=False)
            self.dropped += 1

    def _event(self, v: _Vehicle, msg: Any, now: float) -> None:
        if msg.event == m.START:
            if v.open is not None:
                self.skip("START without END")
                self._forget(v, v.open.index, v.open.start_stamp)
            stamp = m.nanoseconds(msg.header.stamp)
            v.open = _Open(int(msg.episode), int(msg.seed),
                           np.array([msg.goal.x, msg.goal.y, msg.goal.z], np.float64),
                           stamp, v.last_end_stamp == stamp, m.episode_limits(msg))
        elif msg.event == m.END:
            ep, v.open = v.open, None
            v.last_end_stamp = m.nanoseconds(msg.header.stamp)
            if ep is None or ep.index != int(msg.episode):
                self.skip("END without START")
                return
            ep.steps, ep.outcome = int(msg.steps), m.outcome_name(msg)
            ep.end_stamp = m.nanoseconds(msg.header.stamp)
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
                elif now >= ep.deadline:
                    self.skip(f"missing {reason}")
                else:
                    keep.append(ep)
                    continue
                self._forget(v, ep.index, ep.end_stamp)
            v.closed = keep
        return out

    def _try(self, v: _Vehicle, ep: _Open) -> tuple[EpisodeSteps | None, str | None]:
        T = ep.steps
        stamps = sorted(s for s in v.truth if ep.start_stamp <= s <= ep.end_stamp)
        first = 1 if ep.shared_start else 0
        if T < 1 or len(stamps) != T + 1 or len(v.truth[stamps[0]]) <= first:
            return None, "truth"
        actions = [v.commands.get(s) for s in stamps[:T]]
        if any(a is None for a in actions):
            return None, "actions"
        got = {k: v.observations.get((ep.index, k)) for k in range(T + 1)}
        if any(got[k] is None for k in range(T)):
            return None, "observations"
        records = None
        if v.sends_records:
            records = {k: v.records.get((ep.index, k)) for k in range(1, T + 1)}
            if any(r is None for r in records.values()):
                return None, "step records"
        obs = {k: o[0] for k, o in got.items() if o is not None}
        scalings = [o[1] for o in got.values() if o is not None]
        truth = [v.truth[stamps[0]][first]] + [v.truth[s][0] for s in stamps[1:]]
        return EpisodeSteps(ep.goal, T, ep.outcome, obs, truth, actions, scalings,
                            ep.limits, records), None

    def _forget(self, v: _Vehicle, index: int, stamp: int) -> None:
        """Drop the observations of episodes up to ``index`` and the poses and commands
        stamped before ``stamp`` (an episode's last stamp is the next one's first)."""
        for table in (v.observations, v.records):
            for key in [k for k in table if k[0] <= index]:
                del table[key]
        for table in (v.commands, v.truth):
            for key in [k for k in table if k < stamp]:
                del table[key]

    @property
    def waiting(self) -> int:
        """Closed episodes still waiting for late messages."""
        return sum(len(v.closed) for v in self.vehicles.values())
