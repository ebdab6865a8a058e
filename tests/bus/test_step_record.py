"""The step record (bus.task.StepRecord): made by the simulator's episode core, the env's
outcome, termination and reward derive from it, it crosses the bus and the log, and
training from logs (``--from-logs``, the live learner's assembler) takes the rewards from
it; logs without records still train on recomputed rewards, and a record that disagrees
with its logged step is refused."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from bus import keys
from bus import messages as m
from bus.log.writer import EpisodeLogWriter, read_episodes
from bus.task import TASK, goal_angles
from policy.algorithms.agents import make_goal_reward
from policy.algorithms.replay import ReplayBuffer
from policy.algorithms.rewards import RewardConfig, base_reward, step_reward
from policy.algorithms.scripted import StraightLineController
from policy.logs.episode_assembler import AssemblerConfig, EpisodeAssembler
from policy.logs.logrun import log_env_episodes
from policy.logs.offline import episode_steps, load_logs, rebuild_episode
from policy.logs.transitions import RECORD_ATOL
from policy.training.env import UavNavEnv
from sitl.episode import EpisodeSim

SEED, EPISODES = 40, 3


# ------------------------------------------------------------------- the episode core
def test_the_episode_core_records_each_step():
    """D_pre is the last step's D_cur, the distance and altitude are the true pose's,
    h and g the estimate's goal angles, the outcome the task's rule; a descent into the
    terrain ends in a record of a collision."""
    sim = EpisodeSim()
    sim.reset(np.random.default_rng(3))
    task = replace(TASK, max_steps=400)
    before = sim.goal_distance()
    record = None
    for k in range(1, 400):
        sim.step_body(np.array([0.5, 0.0, -2.0, 0.1]))
        record = sim.record(task, episode=7)
        est, truth = sim.vehicle.estimate, sim.vehicle.truth
        assert (record.episode, record.step) == (7, k)
        assert record.distance_before == before
        assert record.distance == float(np.linalg.norm(truth.position - sim.goal))
        assert record.altitude == float(truth.position[2])
        assert (record.h, record.g) == goal_angles(est.position, est.yaw, est.velocity,
                                                   sim.goal)
        assert record.collided == sim.collided
        assert record.outcome == task.outcome(sim.collided, record.distance,
                                              record.altitude, k)
        before = record.distance
        if record.outcome is not None:
            break
    assert record is not None and record.collided and record.outcome == "collision"
    assert record.terminated and not record.truncated and not record.goal_reached


def test_the_env_takes_reward_and_ends_from_the_record():
    """Each step's reward is eq. 3.5 of its record (the same number), the flags are the
    record's, and the record's h, g are the observation's."""
    env = UavNavEnv(scenario="valley")
    ctrl = StraightLineController()
    ends = set()
    for seed in (SEED, SEED + 1):
        state, info = env.reset(seed=seed)
        d = info["distance_to_goal"]
        done = False
        while not done:
            state, reward, terminated, truncated, info = env.step(ctrl(state))
            rec = info["record"]
            assert rec is env.record and rec.step == env.steps
            assert reward == step_reward(rec, env.reward_config)[0]
            assert (terminated, truncated) == (rec.terminated, rec.truncated)
            assert (info["collision"], info["goal_reached"]) == (rec.collided,
                                                                 rec.goal_reached)
            assert rec.distance_before == d and rec.distance == info["distance_to_goal"]
            d = rec.distance
            h, g = state[-1, TASK.faces + 1:] * 180.0  # default scaling, float32
            assert abs(h - rec.h) < 1e-3 and abs(g - rec.g) < 1e-3
            if not rec.collided:
                assert reward == base_reward(rec.distance_before, rec.distance,
                                             rec.altitude, rec.h, rec.g,
                                             env.reward_config)[0]
            done = terminated or truncated
        ends.add(rec.outcome)
    assert ends <= {"success", "collision", "timeout"}


def test_the_message_carries_the_record_and_refuses_what_it_cannot_be():
    rec = TASK.step_record(4, 12, 10.25, 9.75, 3.4, 359.5, 0.25, False)
    assert rec.outcome is None
    back = m.step_record_values(m.decode(m.STEP_RECORD, m.encode(m.step_record(rec, 1.2))))
    assert back == rec
    end = TASK.step_record(4, 13, 1.0, 0.5, 3.4, 1.0, 2.0, True)
    assert m.step_record_values(m.decode(m.STEP_RECORD, m.encode(
        m.step_record(end, 1.3)))).outcome == "collision"
    assert keys.msgtype(keys.STEP_RECORD) == m.STEP_RECORD
    msg = m.step_record(rec, 1.2)
    msg.outcome = m.OUTCOMES["aborted"]  # a sim's decision, END's: not the task's rule
    with pytest.raises(ValueError, match="outcome"):
        m.step_record_values(msg)
    msg = m.step_record(replace(rec, h=math.nan), 1.2)
    with pytest.raises(ValueError, match="non-finite"):
        m.step_record_values(msg)


# ------------------------------------------------------------------------ from logs
@pytest.fixture(scope="module")
def logged(tmp_path_factory):
    """A log of scripted env episodes (with step records) and the env's own rewards."""
    out = tmp_path_factory.mktemp("records")
    env = UavNavEnv(scenario="valley")
    path = log_env_episodes(env, StraightLineController(), EPISODES, SEED, out)
    rewards = []
    ctrl = StraightLineController()
    for i in range(EPISODES):
        state, _ = env.reset(seed=SEED + i)
        got, done = [], False
        while not done:
            state, r, term, trunc, _ = env.step(ctrl(state))
            got.append(r)
            done = term or trunc
        rewards.append(np.array(got))
    return path, rewards


def rewrite(path, out, change) -> object:
    """A copy of the log at ``path`` in ``out`` with ``change(episode, name, decoded)``
    applied to every message (None: left out); returns the new file."""
    episodes, _ = read_episodes(path)
    w = EpisodeLogWriter(out, run_name="rewritten")
    for ep in episodes:
        for msg in ep.messages:
            decoded = change(ep, msg.name, msg.decode())
            if decoded is not None:
                w.write_msg(ep.vehicle, msg.name, decoded, log_time_ns=msg.log_time_ns)
    w.close()
    return w.paths[0]


def test_a_log_carries_records_and_from_logs_takes_the_rewards_from_them(logged):
    """The rewards rebuilt from a log with records are the env's to the bit (no float32
    round trip of h and g)."""
    path, rewards = logged
    episodes, _ = read_episodes(path)
    for ep, expected in zip(episodes, rewards, strict=True):
        steps = episode_steps(ep)
        assert steps.records is not None and sorted(steps.records) == list(
            range(1, ep.steps + 1))
        assert {r.episode for r in steps.records.values()} == {ep.index}
        assert steps.records[ep.steps].outcome == (None if ep.outcome == "aborted"
                                                   else ep.outcome)
        np.testing.assert_array_equal(rebuild_episode(ep, RewardConfig()).rewards, expected)


def test_an_old_log_without_records_still_trains_on_recomputed_rewards(logged, tmp_path):
    """A log made before step records existed: the rewards are recomputed from the truth
    poses and the observations (the env's to float32 rounding), and it trains."""
    path, rewards = logged
    old = rewrite(path, tmp_path, lambda ep, name, msg: None if name == keys.STEP_RECORD
                  else msg)
    episodes, _ = read_episodes(old)
    for ep, expected in zip(episodes, rewards, strict=True):
        assert not ep.topic(keys.STEP_RECORD) and episode_steps(ep).records is None
        np.testing.assert_allclose(rebuild_episode(ep, RewardConfig()).rewards, expected,
                                   rtol=0, atol=1e-5)
    buf = ReplayBuffer(2000, (3, 35), 4)
    report = load_logs([old], buf, make_goal_reward("abr", RewardConfig()), RewardConfig())
    assert report.episodes_used == EPISODES and report.transitions == sum(map(len, rewards))


def test_a_record_that_disagrees_with_its_logged_step_is_refused(logged, tmp_path):
    """A record whose reward is off by more than float32 rounding (h moved by 1 degree),
    or whose outcome contradicts END, refuses the episode, counted with the reason."""
    path, _ = logged

    def moved_h(ep, name, msg):
        if name == keys.STEP_RECORD and ep.index == 0 and msg.step == 5:
            msg.h = (msg.h + 1.0) % 360.0
        return msg

    def no_end(ep, name, msg):
        if name == keys.STEP_RECORD and ep.index == 1 and msg.step == ep.steps:
            msg.outcome, msg.collided = m.OUTCOMES["none"], False
        return msg

    def missing(ep, name, msg):
        keep = not (name == keys.STEP_RECORD and ep.index == 2 and msg.step == 3)
        return msg if keep else None

    assert 1.0 / 180.0 > RECORD_ATOL  # 1 degree of h moves the reward by w3 / 180
    for change, reason in ((moved_h, "inconsistent: step record 5 gives reward"),
                           (no_end, "inconsistent: step record"),
                           (missing, "inconsistent: step records for steps [1, 2, 4]")):
        bad = rewrite(path, tmp_path / change.__name__, change)
        buf = ReplayBuffer(2000, (3, 35), 4)
        report = load_logs([bad], buf, make_goal_reward("tr", RewardConfig()),
                           RewardConfig())
        assert report.episodes_used == EPISODES - 1, report.skipped
        (why, n), = report.skipped.items()
        assert n == 1 and why.startswith(reason), why


# -------------------------------------------------------------------- live learner
def live(ep, drop=lambda name, msg: False) -> list[tuple[str, object]]:
    """A logged episode's messages as the learner's subscriptions deliver them."""
    return [(x.name, x.decode()) for x in ep.messages if not drop(x.name, x.decode())]


def test_the_assembler_joins_records_and_waits_for_them_once_a_vehicle_sends_them(logged):
    path, rewards = logged
    episodes, _ = read_episodes(path)
    ep = episodes[0]
    # a vehicle that sends records: they come with the episode, rewards to the bit
    asm = EpisodeAssembler()
    for name, msg in live(ep):
        asm.add("uav1", name, msg, 0.0)
    (_, _, steps), = asm.poll(0.0)
    assert steps.records == episode_steps(ep).records
    rebuilt = rebuild_episode(ep, RewardConfig())
    from policy.logs.transitions import transitions_from_steps

    np.testing.assert_array_equal(transitions_from_steps(steps, RewardConfig()).rewards,
                                  rewards[0])
    np.testing.assert_array_equal(rebuilt.rewards, rewards[0])
    # an older sim (no records at all): the episode is whole without them
    asm = EpisodeAssembler()
    for name, msg in live(ep, lambda name, msg: name == keys.STEP_RECORD):
        asm.add("uav2", name, msg, 0.0)
    (_, _, steps), = asm.poll(0.0)
    assert steps.records is None
    np.testing.assert_allclose(transitions_from_steps(steps, RewardConfig()).rewards,
                               rewards[0], rtol=0, atol=1e-5)
    # a sim that sends records but one is lost: waited for, then skipped and counted
    asm = EpisodeAssembler(AssemblerConfig(grace_s=1.0))
    for name, msg in live(ep, lambda name, msg: name == keys.STEP_RECORD and msg.step == 2):
        asm.add("uav3", name, msg, 0.0)
    assert asm.poll(0.5) == [] and asm.waiting == 1
    assert asm.poll(1.5) == [] and asm.skipped == {"missing step records": 1}
