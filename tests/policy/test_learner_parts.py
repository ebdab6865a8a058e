"""The actor-learner's parts: the episode assembler (pure), the weight swap in a policy
node's follower and the learner node over a real in-process Zenoh bus (no sims)."""

from __future__ import annotations

import hashlib
import math
import time

import numpy as np
import pytest
import torch
from loopback import free_port, wait_for

from bus import keys
from bus import messages as m
from bus.node import Bus
from bus.session import SessionConfig
from perception.observation import ObservationConfig, scaling_fields
from policy.algorithms.rewards import RewardConfig
from policy.algorithms.td3 import ACTOR_FORMAT, TD3, TD3Config
from policy.logs.episode_assembler import EpisodeAssembler
from policy.logs.transitions import transitions_from_steps
from policy.nodes.learner import LearnerConfig
from policy.nodes.learner_node import Learner
from policy.nodes.weights import WeightsFollower, actor_weights_message
from policy.training.evaluate import SHIPPED_POLICY, ActorController

PERIOD_NS = 100_000_000
SCALING = scaling_fields(ObservationConfig())  # as the perception node records it


def episode_messages(index: int, T: int, g0: int, outcome: str = "timeout",
                     seed: int = 7, scaling=SCALING) -> list[tuple[str, object]]:
    """One episode of a vehicle in the stack's order (the sim's events and truth, the
    perception's observations, the bridge's body-frame commands), stamps from step g0."""
    rng = np.random.default_rng(seed + index)
    goal = (10.0, 5.0, 3.5)
    out: list[tuple[str, object]] = [
        (keys.EPISODE, m.episode_start(index, seed + index, (0, 0, 3.5), goal, g0 * 0.1))]
    for k in range(T + 1):
        t = (g0 + k) * PERIOD_NS / 1e9
        out.append((keys.TRUTH, m.odometry((0.3 * k, 0.1 * k, 3.5), (1, 0, 0), (0, 0, 0, 1), t)))
        if k < T:
            obs = rng.uniform(0, 1, 35).astype(np.float32)
            out.append((keys.OBSERVATION, m.observation(obs, t, index, k, scaling=scaling)))
            a = rng.uniform(-2, 2, 4).astype(np.float32)
            out.append((keys.CMD_VEL, m.velocity_setpoint(a[:3], a[3], t, body=True)))
    out.append((keys.EPISODE, m.episode_end(index, outcome, T, (g0 + T) * 0.1, seed + index)))
    return out


def feed(asm: EpisodeAssembler, vehicle: str, msgs, now: float = 0.0) -> None:
    for topic, msg in msgs:
        asm.add(vehicle, topic, msg, now)


# ----------------------------------------------------------------------------- assembler
def test_complete_episodes_of_two_vehicles_interleaved():
    asm = EpisodeAssembler()
    a, b = episode_messages(0, 5, 0), episode_messages(3, 4, 100, "collision")
    for i in range(max(len(a), len(b))):  # interleaved as two live vehicles would be
        feed(asm, "uav1", a[i:i + 1])
        feed(asm, "uav2", b[i:i + 1])
    done = {v: (i, s) for v, i, s in asm.poll(0.0)}
    assert set(done) == {"uav1", "uav2"} and asm.complete == 2 and not asm.skipped
    i, steps = done["uav2"]
    assert i == 3 and steps.steps == 4 and steps.outcome == "collision"
    cmds = [m.setpoint_values(x) for t, x in b if t == keys.CMD_VEL]
    assert steps.actions == [tuple(float(v) for v in c) for c in cmds]
    tr = transitions_from_steps(steps, RewardConfig())
    assert tr.states.shape == (4, 3, 35) and tr.terminal and not tr.reached
    assert tr.rewards[-1] == RewardConfig().collision


def test_observations_must_say_how_they_were_scaled():
    """Rewards un-scale h and g with what the observations record: an episode whose
    observations do not record it, or record two scalings, is refused by name."""
    other = scaling_fields(ObservationConfig(angle_scale=90.0))
    mixed = episode_messages(1, 4, 50)
    k = next(i for i, (t, _) in enumerate(mixed) if t == keys.OBSERVATION)
    _, first = mixed[k]
    mixed[k] = (keys.OBSERVATION, m.observation(m.observation_values(first), 5.0, 1, 0,
                                                scaling=other))
    for msgs, why in ((episode_messages(0, 4, 0, scaling=None), "without their scaling"),
                      (mixed, "scaled 2 ways")):
        asm = EpisodeAssembler()
        feed(asm, "uav1", msgs)
        [(_, _, steps)] = asm.poll(0.0)
        with pytest.raises(ValueError, match=why):
            transitions_from_steps(steps, RewardConfig())


def test_an_episode_run_under_other_goal_limits_is_refused():
    """START records the goal limits the sim ran the episode under; the assembler keeps
    them and a learner of the default task refuses an episode flown to a 3-m radius by
    name (its success would mean something else), while a learner of that task takes it."""
    from dataclasses import replace

    from bus.task import TASK

    wide = replace(TASK, goal_radius=3.0)
    msgs = episode_messages(0, 4, 0, "success")
    msgs[0] = (keys.EPISODE, m.episode_start(0, 7, (0, 0, 3.5), (10.0, 5.0, 3.5), 0.0,
                                             task=wide))
    asm = EpisodeAssembler()
    feed(asm, "uav1", msgs)
    [(_, _, steps)] = asm.poll(0.0)
    assert steps.limits == {"max_steps": 300.0, "goal_radius": 3.0, "goal_max_altitude": 6.0}
    with pytest.raises(ValueError, match=r"run under goal_radius 3 \(this task: 2\)"):
        transitions_from_steps(steps, RewardConfig())
    assert transitions_from_steps(steps, RewardConfig(), wide).reached


def test_late_command_after_end_is_joined_by_stamp():
    msgs = episode_messages(0, 3, 10)
    last_cmd = [i for i, (t, _) in enumerate(msgs) if t == keys.CMD_VEL][-1]
    late = msgs.pop(last_cmd)
    asm = EpisodeAssembler()
    feed(asm, "uav1", msgs)
    assert asm.poll(0.5) == [] and asm.waiting == 1  # within the grace: waits
    feed(asm, "uav1", [late], 0.6)
    [(_, _, steps)] = asm.poll(0.7)
    assert len(steps.actions) == 3 and asm.waiting == 0 and not asm.skipped


def test_missing_step_is_skipped_after_the_grace_and_counted():
    msgs = [x for x in episode_messages(0, 4, 0)
            if not (x[0] == keys.OBSERVATION and x[1].step == 2)]
    asm = EpisodeAssembler()
    feed(asm, "uav1", msgs)
    assert asm.poll(1.0) == [] and not asm.skipped  # might still come
    assert asm.poll(2.5) == [] and asm.skipped == {"missing observations": 1}
    assert asm.waiting == 0
    feed(asm, "uav1", episode_messages(1, 3, 10))  # the next episode is unaffected
    assert len(asm.poll(3.0)) == 1


def test_end_without_start_and_start_without_end_are_counted():
    first = episode_messages(0, 3, 0)
    asm = EpisodeAssembler()
    feed(asm, "uav1", first[1:])  # the learner joined mid-episode: no START
    feed(asm, "uav1", episode_messages(1, 3, 10)[:-1])  # no END: the next START comes
    feed(asm, "uav1", episode_messages(2, 3, 20))
    out = asm.poll(0.0)
    assert [i for _, i, _ in out] == [2]
    assert asm.skipped == {"END without START": 1, "START without END": 1}


def test_messages_grouped_by_topic_still_assemble():
    """Zenoh delivers each subscription on its own: the END may come before the steps."""
    msgs = episode_messages(0, 4, 0) + episode_messages(1, 3, 4)  # stamp 4 twice
    order = (keys.EPISODE, keys.CMD_VEL, keys.OBSERVATION, keys.TRUTH)
    asm = EpisodeAssembler()
    for topic in order:
        feed(asm, "uav1", [x for x in msgs if x[0] == topic])
        if topic != order[-1]:
            assert asm.poll(0.0) == []
    done = asm.poll(0.0)
    assert [i for _, i, _ in done] == [0, 1] and not asm.skipped
    [(_, _, first), (_, _, second)] = done
    ends = [x[1] for x in msgs if x[0] == keys.TRUTH]
    assert first.truth[-1] is not second.truth[0]  # the shared stamp's two poses
    np.testing.assert_array_equal(first.truth[-1][0], m.odometry_values(ends[4])[0])
    np.testing.assert_array_equal(second.truth[0][0], m.odometry_values(ends[5])[0])
    v = asm.vehicles["uav1"]
    assert not v.observations and not v.commands and list(v.truth) == [7 * PERIOD_NS]


def test_missing_truth_is_skipped_and_counted():
    msgs = episode_messages(0, 4, 0)
    drop = [i for i, (t, _) in enumerate(msgs) if t == keys.TRUTH][2]
    asm = EpisodeAssembler()
    feed(asm, "uav1", msgs[:drop] + msgs[drop + 1:])
    assert asm.poll(0.0) == [] and not asm.skipped
    assert asm.poll(2.5) == [] and asm.skipped == {"missing truth": 1}


def test_corrupt_payloads_are_counted_not_raised():
    msgs = episode_messages(0, 3, 0)
    bad_obs = m.observation(np.zeros(35, np.float32), 0.1, 0, 1)
    bad_obs.frames = 2  # 35 values said to be 2 x 35
    nan_cmd = m.velocity_setpoint((math.nan, 0, 0), 0, 0.1, body=True)
    asm = EpisodeAssembler()
    out = [x for x in msgs if not (x[0] == keys.OBSERVATION and x[1].step == 1)
           and not (x[0] == keys.CMD_VEL and m.nanoseconds(x[1].header.stamp) == PERIOD_NS)]
    feed(asm, "uav1", out[:3] + [(keys.OBSERVATION, bad_obs), (keys.CMD_VEL, nan_cmd),
                                 (keys.TRUTH, object())] + out[3:])
    assert asm.poll(5.0) == []
    assert asm.skipped == {"corrupt observation": 1, "corrupt cmd_vel": 1,
                           "corrupt truth": 1, "missing actions": 1}


# ----------------------------------------------------------------------------- weights
@pytest.fixture()
def bus():
    with Bus.open(SessionConfig(hub=f"tcp/127.0.0.1:{free_port()}")) as b:
        yield b


def test_weights_swap_only_at_the_episode_boundary_and_bad_blobs_are_rejected(bus):
    controller = ActorController(SHIPPED_POLICY)
    shipped = controller.actor
    follower = WeightsFollower(bus, "uavw", controller)
    pub = bus.publisher(keys.ACTOR, "uavw")
    assert pub.wait_matched(5.0)

    def send(msg, expect_received: int) -> None:
        pub.put(msg)
        wait_for(lambda: follower.received >= expect_received, what="weights message")
        follower.poll()

    small = TD3(TD3Config(hidden=(64, 64)))
    send(actor_weights_message(small, 1), 1)
    blob = b"\x00not a torch file" * 100
    send(m.actor_weights(blob, 2, fmt=ACTOR_FORMAT, sha256=hashlib.sha256(blob).hexdigest()), 2)
    good = TD3(TD3Config(seed=3))
    msg = actor_weights_message(good, 3)
    msg.sha256 = "0" * 64
    send(msg, 3)
    send(m.actor_weights(m.actor_blob(msg), 4, fmt="pickle"), 4)
    with torch.no_grad():
        nan_agent = TD3(TD3Config(seed=4))
        next(nan_agent.actor.parameters())[0, 0] = math.nan
    send(actor_weights_message(nan_agent, 5), 5)
    assert follower.held is None and controller.actor is shipped and follower.version == 0
    assert follower.rejected == {"shapes": 1, "decode": 1, "sha256": 1, "format": 1,
                                 "non-finite": 1}

    send(actor_weights_message(good, 6), 6)  # a good one: held, not flown yet
    assert follower.held is not None and controller.actor is shipped
    send(actor_weights_message(good, 6), 7)  # same version again: stale, ignored
    assert follower.stale == 1
    assert follower.at_episode_boundary(12) == 6 and follower.version == 6
    assert controller.actor is not shipped and follower.history[-1]["episode"] == 12
    state = np.random.default_rng(0).uniform(0, 1, 105).astype(np.float32)
    np.testing.assert_array_equal(controller(state), good.act(state, noise=False))
    assert follower.at_episode_boundary(13) is None  # nothing new: keeps flying 6


# ----------------------------------------------------------------------------- learner
def test_learner_consumes_bus_episodes_publishes_and_resumes(bus, tmp_path):
    cfg = LearnerConfig(vehicles=["uavl"], warmup=0, critic_warmup=0, publish_every=2,
                        max_episodes=2, init_actor="scratch", buffer_size=10_000, grace_s=0.5)
    lines: list[str] = []
    learner = Learner(bus, cfg, tmp_path, emit=lines.append)
    controller = ActorController(SHIPPED_POLICY)
    follower = WeightsFollower(bus, "uavl", controller)
    pubs = {t: bus.publisher(t, "uavl") for t in (keys.EPISODE, keys.OBSERVATION, keys.TRUTH,
                                                  keys.CMD_VEL)}
    assert all(p.wait_matched(5.0) for p in pubs.values())
    assert learner.publishers["uavl"].wait_matched(5.0)
    garbage = bus.publisher(keys.OBSERVATION, "uavl")
    garbage.put_bytes(b"\x00\x01\x00\x00 not CDR")
    for topic, msg in episode_messages(0, 6, 0) + episode_messages(1, 5, 6, "success"):
        pubs[topic].put(msg)
    deadline = time.monotonic() + 60.0  # a learner that never gets there fails below
    summary = learner.run(lambda: time.monotonic() > deadline, progress=False)
    assert summary["episodes"] == 2 and summary["by_vehicle"] == {"uavl": 2}
    assert summary["transitions"] == 11 and summary["updates"] == 11
    assert summary["version"] == 1 and summary["skipped"] == {"undecodable payload": 1}
    assert any(x.startswith("SKYLOOP-LEARNER-PUBLISHED ") for x in lines)
    wait_for(lambda: follower.received == 1, what="published weights")
    follower.poll()
    assert follower.at_episode_boundary(0) == 1
    state = np.ones(105, np.float32)
    np.testing.assert_array_equal(controller(state), learner.agent.act(state, noise=False))

    with pytest.raises(FileExistsError):
        Learner(bus, cfg, tmp_path, emit=lines.append)
    resumed = Learner(bus, LearnerConfig(**{**cfg.__dict__, "resume": True,
                                           "vehicles": ["uavm"]}), tmp_path, emit=lines.append)
    assert (resumed.episodes, resumed.version, resumed.agent.updates) == (2, 1, 11)
    assert len(resumed.buffer) == 11


def test_critic_warmup_leaves_the_actor_as_it_was():
    from perception.observation import FrameStacker
    from policy.algorithms.replay import ReplayBuffer

    agent = TD3(TD3Config(seed=5))
    buf = ReplayBuffer(100, (3, 35), 4, seed=0)
    rng = np.random.default_rng(0)
    stacker = FrameStacker(3, 35)  # the buffer takes frame stacks
    state = stacker.push(rng.uniform(0, 1, 35))
    for _ in range(50):
        next_state = stacker.push(rng.uniform(0, 1, 35))
        buf.add(state, rng.uniform(-2, 2, 4), rng.normal(), next_state, False)
        state = next_state
    def same(before, module) -> bool:
        return all(torch.equal(a, b) for a, b in zip(before, module.parameters(), strict=True))

    actor0 = [p.clone() for p in agent.actor.parameters()]
    critic0 = [p.clone() for p in agent.critic.parameters()]
    for _ in range(4):
        out = agent.update(buf.sample(10), train_actor=False)
        assert "actor_loss" not in out
    assert same(actor0, agent.actor) and not same(critic0, agent.critic)
    agent.update(buf.sample(10))
    assert "actor_loss" in agent.update(buf.sample(10))
    assert not same(actor0, agent.actor)


def test_learner_serves_every_vehicle_it_sees(bus, tmp_path):
    """``--vehicles '*'``: episodes of any vehicle, weights to each vehicle seen."""
    cfg = LearnerConfig(warmup=0, critic_warmup=0, max_episodes=2, init_actor="scratch",
                        buffer_size=1000, grace_s=0.5)
    learner = Learner(bus, cfg, tmp_path, emit=lambda line: None)
    followers = {v: WeightsFollower(bus, v, ActorController(SHIPPED_POLICY))
                 for v in ("uavx", "uavy")}
    for i, v in enumerate(followers):
        pubs = {t: bus.publisher(t, v) for t in (keys.EPISODE, keys.OBSERVATION, keys.TRUTH,
                                                 keys.CMD_VEL)}
        assert all(p.wait_matched(5.0) for p in pubs.values())
        for topic, msg in episode_messages(i, 4, 10 * i):
            pubs[topic].put(msg)
    deadline = time.monotonic() + 60.0
    summary = learner.run(lambda: time.monotonic() > deadline, progress=False)
    assert summary["by_vehicle"] == {"uavx": 1, "uavy": 1} and summary["version"] >= 1
    assert set(learner.publishers) == {"uavx", "uavy"}
    wait_for(lambda: all(f.received for f in followers.values()), what="weights to both")
