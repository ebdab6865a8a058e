"""When a control step of the simulator node runs and which command answers it: the
node's clocks (:class:`StackClock`), wall-clock pacing (:class:`Pacer`), the lockstep
and real-time command gate (:class:`CommandGate`) and what the node keeps after lockstep
broke (:class:`Rejoin`). The rules are in ``sitl/node/node.py``'s docstring ("Clocks")."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from bus import messages as m
from sitl.commander.machine import Commander, State

log = logging.getLogger("skyloop.sim")
POLL_S = 0.01  # s, how often requests are served while the node waits


class StackClock:
    """The node's two clocks, both counted in control periods (integer ns: exact).

    ``g`` counts episode steps over the run: the stack time that stamps what the node
    publishes. ``vsteps`` counts every control step flown (ground phase included): the
    commander's clock, which never goes backwards."""

    def __init__(self, period_ns: int) -> None:
        self.period_ns = period_ns
        self.period = period_ns / 1e9
        self.g = 0
        self.vsteps = 0

    def stamp(self) -> float:
        """Stack time (s) of the current episode step."""
        return self.g * self.period_ns / 1e9

    def stamp_ns(self) -> int:
        """Stack time (ns) of the current episode step: what its command is stamped."""
        return self.g * self.period_ns

    def now(self) -> float:
        """The commander's clock: control steps flown since start, in seconds."""
        return self.vsteps * self.period_ns / 1e9

    def advance(self, episode_step: bool) -> None:
        """One control step flown (an episode's step also advances stack time)."""
        self.vsteps += 1
        if episode_step:
            self.g += 1


class Pacer:
    """Wall-clock pacing: :meth:`pace` waits for the next tick of the control period,
    calling ``serve`` (requests, commands, status) every :data:`POLL_S` meanwhile; a
    step that falls behind by more than a period drops the missed ticks instead of
    bursting. :meth:`release` forgets the tick (a lockstep step, or a wait that is not
    paced): the next paced step starts at once."""

    def __init__(self, period: float, serve: Callable[[], None]) -> None:
        self.period = period
        self.serve = serve
        self._next_tick: float | None = None

    def release(self) -> None:
        self._next_tick = None

    def serve_until(self, deadline: float) -> None:
        """Serve until the wall-clock ``deadline`` (at least once)."""
        while True:
            self.serve()
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            time.sleep(min(POLL_S, remaining))

    def pace(self) -> float:
        """Wait for this step's tick; return the step's deadline (the next tick)."""
        if self._next_tick is None:
            self._next_tick = time.monotonic()
        self.serve_until(self._next_tick)
        self._next_tick = max(self._next_tick + self.period, time.monotonic() - self.period)
        return self._next_tick


class Rejoin:
    """What the node keeps after lockstep broke, so that it joins the policy again: the
    only state that outlives a step or an episode on the command path.

    * :attr:`missing` (step level): a lockstep command did not come within the lockstep
      timeout and none has matched since, so each further step waits one control period
      only (the commander's setpoint-loss failsafe then acts within seconds). A matching
      command clears it, and so does every episode start (:meth:`episode_started`): an
      episode waits the full timeout for its first command.
    * :attr:`since`, :attr:`late_stamp` (episode level): a seeded episode ended
      ``aborted`` at commander time ``since`` because the vehicle left OFFBOARD or a
      step's command did not come (:meth:`broke`). Before the next episode the node flies
      outside any episode until :meth:`rejoined`: the vehicle is in OFFBOARD asked for
      after ``since`` (a restarted policy asks once it can answer steps; a companion
      still starting may stream setpoints already, which is not enough), or, still in
      OFFBOARD, the newest command is the late answer to the step whose command did not
      come (``late_stamp``; the policy is alive, only slow, e.g. on a loaded machine).
      :meth:`clear` then forgets the break.
    """

    def __init__(self) -> None:
        self.missing = False
        self.since: float | None = None
        self.late_stamp: int | None = None

    # ---- step level (the command gate)
    def lockstep_wait(self, timeout_s: float, period: float) -> float:
        """How long a lockstep step waits for its command (wall seconds)."""
        return period if self.missing else timeout_s

    def command_missed(self) -> bool:
        """A step's command did not come; True if the one before had come (say so once)."""
        first = not self.missing
        self.missing = True
        return first

    def command_matched(self) -> None:
        self.missing = False

    def episode_started(self) -> None:
        self.missing = False

    # ---- episode level (the episode runner)
    def broke(self, now: float, late_stamp: int | None) -> None:
        """The episode ended ``aborted`` at commander time ``now``; ``late_stamp``: the
        stamp (ns) of the step whose command did not come, if that was why."""
        self.since, self.late_stamp = now, late_stamp

    @property
    def pending(self) -> bool:
        """An episode broke and the vehicle has not rejoined since."""
        return self.since is not None

    def rejoined(self, commander: Commander, last_command: Any) -> bool:
        """The vehicle is in OFFBOARD asked for after the break, or the newest command
        (``last_command``) answers the step that missed (see the class docstring)."""
        if commander.state != State.OFFBOARD or self.since is None:
            return False
        late = self.late_stamp is not None and last_command is not None and \
            m.nanoseconds(last_command.header.stamp) == self.late_stamp
        return commander.offboard_asked > self.since or late

    def clear(self) -> None:
        self.since = self.late_stamp = None


class CommandGate:
    """Which ``cmd_vel`` (``VelocitySetpoint``) answers which step.

    Every command taken from the inbox is offered to the commander (OFFBOARD needs a
    recent one). :meth:`wait` returns the command stamped with the current step
    (:meth:`StackClock.stamp_ns`): in lockstep it waits up to the lockstep timeout (one
    period while :attr:`Rejoin.missing`), counting a step flown without it in
    ``missed``; in real time until the step's deadline, then the newest command not
    from the future, counting ``late``. Commands stamped otherwise are counted
    ``stale``. While it waits, ``serve`` answers requests; a request that takes the
    vehicle out of OFFBOARD ends the wait (None). ``latencies_ms``: scan publish ->
    matching command back. ``last``: the newest command taken (the real-time fallback,
    and what :meth:`Rejoin.rejoined` checks)."""

    def __init__(self, inbox: Any, commander: Commander, clock: StackClock, rejoin: Rejoin,
                 timeout_s: float, serve: Callable[[], None]) -> None:
        self.inbox = inbox
        self.commander = commander
        self.clock = clock
        self.rejoin = rejoin
        self.timeout_s = timeout_s
        self.serve = serve
        self.last: Any = None
        self.stale = 0  # commands whose stamp was not the current step's
        self.late = 0  # real time: steps flown on an older command
        self.missed = 0  # lockstep: OFFBOARD steps flown without their command
        self.latencies_ms: list[float] = []

    def offer(self, msg: Any) -> None:
        """Offer a command to the commander."""
        vx, vy, vz, yaw = m.setpoint_values(msg)
        self.commander.setpoint(self.clock.now(), vx, vy, vz, 0.0 if msg.heading else yaw,
                                body=msg.frame == m.FRAME_BODY,
                                yaw=yaw if msg.heading else None)

    def drain(self) -> None:
        """Offer every queued command (no step waits for one)."""
        while (msg := self.inbox.get_nowait()) is not None:
            self.offer(msg)
            self.last = msg

    def take(self, timeout: float) -> bool:
        """Offer the next command (waiting up to ``timeout`` s) and any behind it; True
        if one came (``VehicleService.take_setpoints``: an OFFBOARD request served right
        behind its setpoint)."""
        try:
            msg = self.inbox.get(timeout=timeout)
        except TimeoutError:
            return False
        self.offer(msg)
        self.last = msg
        self.drain()
        return True

    def wait(self, t_pub: float, deadline: float | None) -> Any:
        """The command stamped with the current step. Lockstep (``deadline`` None): wait
        for it, None if it did not come; real time: until ``deadline``, then the newest
        command seen (see the class docstring)."""
        want = self.clock.stamp_ns()
        if deadline is None:
            wait = self.rejoin.lockstep_wait(self.timeout_s, self.clock.period)
            give_up = time.monotonic() + wait
        while True:
            end = give_up if deadline is None else deadline
            remaining = end - time.monotonic()
            if remaining <= 0:
                if deadline is not None:
                    self.late += 1
                    return self.last
                self.missed += 1
                if self.rejoin.command_missed():
                    log.warning("lockstep: no command for stack time %.1f s within %.1f s "
                                "(wall); stepping without it", want / 1e9, wait)
                return None
            try:
                msg = self.inbox.get(timeout=min(POLL_S, remaining))
            except TimeoutError:
                self.serve()
                if self.commander.state != State.OFFBOARD:  # a request changed the mode
                    return None
                continue
            self.offer(msg)
            stamp = m.nanoseconds(msg.header.stamp)
            if stamp == want:
                self.latencies_ms.append((time.monotonic() - t_pub) * 1e3)
                self.last = msg
                self.rejoin.command_matched()
                return msg
            self.stale += 1
            if deadline is not None and stamp < want:
                self.last = msg
