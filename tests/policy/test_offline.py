"""Training from logs: transitions and rewards rebuilt from an episode log, bad logs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bus.log.writer import read_episodes
from perception.observation import ObservationConfig
from policy.algorithms.agents import make_goal_reward
from policy.algorithms.replay import ReplayBuffer
from policy.algorithms.rewards import RewardConfig
from policy.algorithms.scripted import StraightLineController
from policy.logs.logrun import log_env_episodes
from policy.logs.offline import (
    file_observations,
    load_logs,
    rebuild_episode,
    train_from_logs,
)
from policy.training.env import UavNavEnv

SEED, EPISODES = 40, 3


def log_and_fly(out, obs_config: ObservationConfig | None = None, episodes: int = EPISODES):
    """A log of scripted episodes and the env's own record of the same episodes."""
    env = UavNavEnv(scenario="valley", observation_config=obs_config)
    path = log_env_episodes(env, StraightLineController(obs=obs_config), episodes, SEED, out)
    truth = []
    ctrl = StraightLineController(obs=obs_config)
    for i in range(episodes):
        state, _ = env.reset(seed=SEED + i)
        rewards, actions, done = [], [], False
        while not done:
            a = ctrl(state)
            state, r, term, trunc, info = env.step(a)
            rewards.append(r)
            actions.append(np.clip(a, -2, 2))
            done = term or trunc
        truth.append((np.array(rewards), np.array(actions, np.float32), info))
    return path, truth


@pytest.fixture(scope="module")
def logged(tmp_path_factory):
    return log_and_fly(tmp_path_factory.mktemp("logs"))


def test_rebuilt_transitions_match_the_env(logged):
    path, truth = logged
    episodes, report = read_episodes(path)
    assert len(episodes) == EPISODES and report.clean
    for ep, (rewards, actions, info) in zip(episodes, truth, strict=True):
        tr = rebuild_episode(ep, RewardConfig())
        assert tr.actions.shape == actions.shape and np.array_equal(tr.actions, actions)
        np.testing.assert_allclose(tr.rewards, rewards, atol=1e-4)
        assert tr.reached == info["goal_reached"]
        assert tr.terminal == (info["goal_reached"] or info["collision"])
        assert np.all(tr.states[0][:2] == 0)  # zero-padded at the episode start
        assert np.array_equal(tr.next_states[:-1], tr.states[1:])


def test_an_observation_logged_in_the_previous_episode_is_joined_by_its_fields(logged):
    """In a stack log the next episode's first observation can lie before its START
    (perception's path through the bus is longer than the sim's): it must neither
    replace the ended episode's step 0 nor go missing from its own episode."""
    path, _ = logged
    episodes, _ = read_episodes(path)
    whole = [rebuild_episode(ep, RewardConfig()) for ep in episodes[:2]]
    first, second = episodes[0], episodes[1]
    early = second.topic("observation")[0]
    assert early.decode().step == 0
    second.messages.remove(early)  # as the recorder saw it: before the START
    first.messages.insert(len(first.messages) - 1, early)
    observations = file_observations(path)
    for ep, expected in zip((first, second), whole, strict=True):
        tr = rebuild_episode(ep, RewardConfig(), observations=observations)
        assert np.array_equal(tr.states, expected.states)
        np.testing.assert_array_equal(tr.rewards, expected.rewards)
    # without the file's observations the first episode is still right
    assert np.array_equal(rebuild_episode(first, RewardConfig()).states, whole[0].states)


def test_a_command_answering_the_previous_episode_is_left_out(logged):
    """In a stack log the last command of an episode can reach the recorder after the next
    episode's START (the bridge's path is not the sim's): the next episode takes its
    actions by the steps they answer. (The ended one finds its last among the file's
    commands by stamp in a stack log, whose stamps count over the run:
    tests/stack/test_stack_up.py; this env log's restart each episode.)"""
    path, _ = logged
    episodes, _ = read_episodes(path)
    whole = [rebuild_episode(ep, RewardConfig()) for ep in episodes[:2]]
    first, second = episodes[0], episodes[1]
    late = first.topic("cmd_vel")[-1]
    first.messages.remove(late)
    second.messages.insert(second.messages.index(second.topic("cmd_vel")[0]), late)
    tr = rebuild_episode(second, RewardConfig())
    assert np.array_equal(tr.actions, whole[1].actions)
    np.testing.assert_array_equal(tr.rewards, whole[1].rewards)
    with pytest.raises(ValueError, match="actions for T"):  # its last: not in its range
        rebuild_episode(first, RewardConfig())


def test_rewards_use_the_scaling_the_log_records(tmp_path):
    """A log made under a non-default observation scaling (angles centred and halved in
    range, altitude over 5 m) gives the env's rewards: h and g are un-scaled with what
    the observations record, not with the default configuration."""
    cfg = ObservationConfig(altitude_scale=5.0, angle_scale=90.0, centre_angles=True)
    path, truth = log_and_fly(tmp_path, cfg, episodes=2)
    episodes, _ = read_episodes(path)
    for ep, (rewards, _, _) in zip(episodes, truth, strict=True):
        np.testing.assert_allclose(rebuild_episode(ep, RewardConfig()).rewards, rewards,
                                   atol=1e-4)


def test_training_takes_the_goal_limits_the_log_records(tmp_path):
    """A log flown under a 3-m goal radius trains under it (the summary and the actor
    record it); episodes of another log, flown under the default 2 m, are refused and
    counted with the reason, never trained on as if they meant the same success."""
    from policy.algorithms.td3 import load_actor
    from policy.training.env import EnvConfig

    wide = log_env_episodes(UavNavEnv(scenario="valley", config=EnvConfig(goal_radius=3.0)),
                            StraightLineController(), 2, SEED, tmp_path / "wide")
    default = log_env_episodes(UavNavEnv(scenario="valley"), StraightLineController(), 2,
                               SEED, tmp_path / "default")
    summary = train_from_logs([wide, default], tmp_path / "run", reward="tr", updates=2)
    assert summary["episodes_used"] == 2 and summary["task"]["goal_radius"] == 3.0
    assert summary["skipped"] == {"inconsistent: episode run under goal_radius 2 "
                                  "(this task: 3)": 2}
    assert load_actor(tmp_path / "run" / "actor.pt").trained_task.goal_radius == 3.0
    buf = ReplayBuffer(1000, (3, 35), 4)  # the default log alone trains under 2 m
    report = load_logs([default], buf, make_goal_reward("tr", RewardConfig()), RewardConfig())
    assert report.episodes_used == 2 and report.task.goal_radius == 2.0


def test_an_episode_without_recorded_limits_is_refused(logged, tmp_path):
    """A log whose START records no episode limits (goal_radius 0: written by another
    tool, or before the field existed) is refused with the reason, not trained under an
    assumed task."""
    from bus import keys
    from bus.log.writer import EpisodeLogWriter

    path, _ = logged
    episodes, _ = read_episodes(path)
    w = EpisodeLogWriter(tmp_path, run_name="nolimits")
    for ep in episodes[:1]:
        for msg in ep.messages:
            decoded = msg.decode()
            if msg.name == keys.EPISODE and decoded.event == 0:  # START
                decoded.goal_radius = 0.0
            w.write_msg(ep.vehicle, msg.name, decoded, log_time_ns=msg.log_time_ns)
    w.close()
    buf = ReplayBuffer(1000, (3, 35), 4)
    report = load_logs([w.dir], buf, make_goal_reward("tr", RewardConfig()), RewardConfig())
    assert report.episodes_used == 0 and report.task is None
    assert report.skipped == {"inconsistent: episode its START records no episode limits "
                              "(goal_radius 0)": 1}


def test_a_split_run_directory_is_read_whole(tmp_path):
    path = log_env_episodes(UavNavEnv(scenario="valley"), StraightLineController(), 3, SEED,
                            tmp_path, split_episodes=1)
    assert len(list(path.parent.glob("*.mcap"))) == 3
    buf = ReplayBuffer(1000, (3, 35), 4)
    report = load_logs([path.parent], buf, make_goal_reward("tr", RewardConfig()),
                       RewardConfig())
    assert report.episodes_used == 3 and len(report.files) == 3


def test_one_log_serves_every_goal_reward(logged):
    path, truth = logged
    n = sum(len(r) for r, _, _ in truth)
    for name in ("tr", "ngr", "egr", "abr"):
        buf = ReplayBuffer(1000, (3, 35), 4)
        report = load_logs([path], buf, make_goal_reward(name, RewardConfig()), RewardConfig())
        assert report.episodes_used == EPISODES and report.transitions == n == len(buf)


def test_incomplete_and_corrupt_logs_are_skipped_and_counted(logged, tmp_path):
    path, truth = logged
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])  # the run died mid-way
    buf = ReplayBuffer(1000, (3, 35), 4)
    report = load_logs([cut, tmp_path / "missing.mcap"], buf,
                       make_goal_reward("ngr", RewardConfig()), RewardConfig())
    assert report.episodes_used < EPISODES
    assert sum(report.skipped.values()) >= 2
    assert any("unreadable" in k for k in report.skipped)
    assert any("incomplete" in k or "corrupt" in k for k in report.skipped)


def test_train_from_logs_writes_an_actor(logged, tmp_path):
    path, _ = logged
    summary = train_from_logs([path], tmp_path / "run", reward="abr", updates=20, bc=True)
    assert summary["episodes_used"] == EPISODES and summary["algo"] == "td3+bc"
    assert (tmp_path / "run" / "actor.pt").stat().st_size > 100_000
    with pytest.raises(ValueError, match="no usable episodes"):
        train_from_logs([tmp_path / "nothing.mcap"], tmp_path / "run2", updates=1)


def test_the_command_learns_from_logs(logged, tmp_path):
    """``skyloop train --from-logs LOG... --out DIR``, with the run's --reward and --seed."""
    path, _ = logged
    out = tmp_path / "cli"
    proc = subprocess.run([sys.executable, "-m", "skyloop", "train", "--from-logs", str(path),
                           "--reward", "egr", "--updates", "3", "--bc", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads((out / "from_logs.json").read_text())
    assert (summary["reward"], summary["updates"], summary["algo"]) == ("egr", 3, "td3+bc")
    assert summary["episodes_used"] == EPISODES and (out / "actor.pt").is_file()


def test_a_file_that_is_not_a_log_is_named(logged, tmp_path):
    """Random bytes or an empty file among the logs: named as not an MCAP file, alone
    (an error) or beside a good log (counted in the summary's skipped, not silent)."""
    path, _ = logged
    noise, empty = tmp_path / "noise.mcap", tmp_path / "empty.mcap"
    noise.write_bytes(np.random.default_rng(0).bytes(5000))
    empty.write_bytes(b"")
    for bad in (noise, empty):
        with pytest.raises(ValueError, match=rf"{bad}: not an MCAP file"):
            train_from_logs([bad], tmp_path / f"run-{bad.stem}", updates=1)
    summary = train_from_logs([path, noise], tmp_path / "mixed", updates=1)
    assert summary["episodes_used"] == EPISODES
    assert summary["skipped"] == {f"{noise}: not an MCAP file (bad magic)": 1}


def test_the_command_names_a_bad_file_alone_or_among_good_ones(logged, tmp_path):
    """``skyloop train --from-logs``: a file that is not a log, alone, is one line naming
    it (exit 2); beside a good log it is skipped and said on stderr, not only counted in
    the JSON."""
    path, _ = logged
    noise = tmp_path / "noise.mcap"
    noise.write_bytes(np.random.default_rng(1).bytes(5000))

    def train(*logs: Path) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "skyloop", "train", "--from-logs",
                               *map(str, logs), "--updates", "1", "--out",
                               str(tmp_path / f"out{len(logs)}")],
                              capture_output=True, text=True, timeout=300)

    alone = train(noise)
    assert alone.returncode == 2, alone.stderr
    assert alone.stderr == (f"skyloop train: error: no usable episodes in {noise}: {noise}: "
                            f"not an MCAP file (bad magic)\n"), alone.stderr
    mixed = train(path, noise)
    assert mixed.returncode == 0, mixed.stderr[-2000:]
    assert (f"skyloop train: skipped 1 episode(s) or file(s): {noise}: not an MCAP file "
            f"(bad magic)\n") in mixed.stderr, mixed.stderr
