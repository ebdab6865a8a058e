"""The simulator node's episodes (:class:`EpisodeRunner`): the flight before "go", each
episode from START to END, and the flight between episodes (waiting for a goal, or for
the vehicle to rejoin after a broken episode). The rules are in ``sitl/node/node.py``'s
docstring ("Phases")."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from bus import keys
from bus import messages as m
from bus.task import TASK
from sitl.commander.machine import State
from sitl.node.pacing import POLL_S, Rejoin
from sitl.node.step import ControlStep, SimNodeConfig
from sitl.node.util import quat_from_matrix, quat_from_yaw

log = logging.getLogger("skyloop.sim")


class EpisodeRunner:
    """Flies :class:`ControlStep` s in and between episodes; ``stopping`` set: the
    episode in progress ends ``aborted`` and every wait returns."""

    def __init__(self, config: SimNodeConfig, step: ControlStep, rejoin: Rejoin,
                 stopping: threading.Event) -> None:
        self.config = config
        self.step = step
        self.rejoin = rejoin
        self.stopping = stopping
        # the parts the steps fly with, by name
        self.sim, self.commander, self.clock = step.sim, step.commander, step.clock
        self.gate, self.goals, self.pub = step.gate, step.goals, step.pub

    def run_episode(self, i: int, goal: np.ndarray | None = None) -> dict:
        """Episode ``i``: seeded and placed airborne, or (``goal`` given) from where the
        vehicle is toward ``goal``."""
        c, s, clock = self.config, self.sim, self.clock
        seed = c.seed + i
        if goal is None:
            s.reset(np.random.default_rng(seed))
            self.commander.place(clock.now(), airborne=True, mode=self.step.resume)
        else:
            s.new_goal(goal)
        task = replace(TASK, max_steps=math.inf if c.free_flight else c.max_steps,
                       goal_radius=c.goal_radius, goal_max_altitude=c.goal_max_altitude)
        self.pub[keys.EPISODE].put(m.episode_start(i, seed, s.start, s.goal, clock.stamp(),
                                                   s.world_name, task))  # NAME#SEED if drawn
        path = [s.vehicle.truth.position.copy()]
        flown = False  # the episode has flown OFFBOARD (seeded: it is placed in OFFBOARD)
        missed = self.gate.missed
        self.rejoin.episode_started()
        while True:
            self.step.tick(i)
            truth = s.vehicle.truth
            path.append(truth.position.copy())
            record = s.record(task, i)  # the outcome by the task's rule, and the log's
            self.pub[keys.STEP_RECORD].put(m.step_record(record, clock.stamp()))
            outcome = record.outcome
            offboard = self.commander.state == State.OFFBOARD
            broken = None if c.free_flight else \
                "the vehicle left OFFBOARD" if flown and not offboard else \
                "a step's command did not come" if self.gate.missed > missed else None
            if outcome is None and (self.goals.pending is not None or self.stopping.is_set()
                                    or broken):
                outcome = "aborted"
                if broken:
                    # the step whose command did not come: its late answer means the
                    # policy is alive, only slow (a loaded machine), so flying goes on
                    late = (clock.g - 1) * clock.period_ns if missed != self.gate.missed \
                        else None
                    self.rejoin.broke(clock.now(), late)
                    log.warning("episode %d aborted at step %d: %s (%s)", i, s.steps, broken,
                                self.commander.state)
            flown = flown or offboard
            if outcome is not None:
                break
        # The terminal pose, for logs (training from logs needs it; only the recorder
        # listens to truth, so the lockstep chain is untouched).
        self.pub[keys.TRUTH].put(m.odometry(truth.position, truth.velocity,
                                            quat_from_matrix(truth.rotation), clock.stamp()))
        self.pub[keys.EPISODE].put(m.episode_end(i, outcome, s.steps, clock.stamp(), seed,
                                                 s.world_name))
        length = float(np.sum(np.linalg.norm(np.diff(np.array(path), axis=0), axis=1)))
        return {"episode": i, "seed": seed, "outcome": outcome, "steps": s.steps,
                "path_length": length}

    def next_goal(self, i: int, outcome: str) -> np.ndarray | None:
        """The goal of episode ``i``, after one that ended ``outcome`` (None: a seeded,
        placed episode; with ``goals_from_bus``: stopping)."""
        if self.goals.pending is not None:
            return self.goals.take()
        if self.config.goals_from_bus:
            if outcome == "collision":  # back on the ground where it fell
                self.place_on_ground(self.sim.vehicle.truth.position)
            return self.wait_goal()
        if not self.config.free_flight:
            if self.rejoin.pending:
                self.wait_rejoin()
                self.rejoin.clear()
            return None
        start, goal = self.sim.world.sample_start_goal(
            np.random.default_rng(self.config.seed + i))
        if outcome == "collision":  # back on the ground at this episode's start
            self.place_on_ground(start)
        return goal

    def wait_rejoin(self) -> None:
        """Seeded episodes, after a broken one: fly control steps outside any episode
        (failsafes, requests, status) until the vehicle rejoins (:class:`Rejoin`); the
        next episode then starts placed as usual."""
        log.info("waiting for OFFBOARD to be asked for again before the next episode")
        while not self.stopping.is_set() and \
                not self.rejoin.rejoined(self.commander, self.gate.last):
            if self.step.tick(None):
                self.place_on_ground(self.sim.vehicle.truth.position)

    def wait_goal(self) -> np.ndarray | None:
        """``goals_from_bus``: fly control steps outside any episode (the commander's
        output, or a hold the policy streams) until a goal comes; None if stopping."""
        while not self.stopping.is_set():
            if self.goals.pending is not None:
                return self.goals.take()
            if self.step.tick(None):
                self.place_on_ground(self.sim.vehicle.truth.position)
            est = self.sim.vehicle.estimate  # telemetry for the bridge (stack time stands)
            self.pub[keys.ODOM].put(m.odometry(est.position, est.velocity,
                                               quat_from_yaw(est.yaw), self.clock.stamp()))
        return None

    def place_on_ground(self, start: np.ndarray) -> None:
        self.sim.place_on_ground(float(start[0]), float(start[1]), self.sim.vehicle.estimate.yaw)
        self.commander.place(self.clock.now(), airborne=False)

    def ground_phase(self, go: Callable[[], Any] | None) -> None:
        """Until "go" (see ``sitl/node/node.py``): on the ground, serving requests; while the
        commander is in OFFBOARD before go, nothing answers steps yet: only requests and
        the status are served."""
        started = threading.Event()
        if go is not None:
            threading.Thread(target=lambda: (go(), started.set()), daemon=True).start()
        pacer, service, clock = self.step.pacer, self.step.service, self.clock
        while not (started.is_set() or self.stopping.is_set()):
            if go is None and (self.config.free_flight
                               or self.commander.state == State.OFFBOARD):
                return
            if self.commander.state == State.OFFBOARD:  # nothing answers steps yet
                pacer.release()
                pacer.serve_until(time.monotonic() + POLL_S)
                service.publish_status(clock.stamp(), clock.now())
                continue
            if self.step.tick(None):
                self.place_on_ground(self.sim.vehicle.truth.position)
        self.step.resume = self.commander.state
