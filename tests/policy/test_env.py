"""The in-process env: Gymnasium contract, determinism, termination rules, bad actions."""

from __future__ import annotations

import dataclasses

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import skyloop  # noqa: F401  (registers skyloop/UavNav-v0)
from policy.algorithms.scripted import StraightLineController
from policy.training.env import EnvConfig, UavNavEnv, body_to_world


@pytest.fixture(scope="module")
def env():
    e = UavNavEnv(scenario="valley")
    yield e
    e.close()


def test_registered_and_makes():
    e = gymnasium.make("skyloop/UavNav-v0", scenario="valley", seed=3, lidar_max_range=4.5)
    state, info = e.reset()
    assert state.shape == (3, 35) and state.dtype == np.float32
    assert e.action_space.shape == (4,)
    assert np.all(e.action_space.low == -2) and np.all(e.action_space.high == 2)
    assert e.unwrapped.lidar.config.max_range == 4.5
    e.close()


def test_passes_gymnasium_env_checker():
    e = UavNavEnv(scenario="valley")
    check_env(e, skip_render_check=True)
    e.close()


def test_first_state_is_zero_padded(env):
    state, _ = env.reset(seed=5)
    assert np.all(state[:2] == 0)
    assert np.any(state[2] != 0)  # altitude and angles are never all zero at the flight level
    state, *_ = env.step(np.zeros(4))
    assert np.all(state[0] == 0) and np.any(state[1] != 0)


def _rollout(env, seed, steps=25):
    state, _ = env.reset(seed=seed)
    ctrl = StraightLineController()
    states, rewards, positions = [state], [], []
    for _ in range(steps):
        state, r, term, trunc, info = env.step(ctrl(state))
        states.append(state)
        rewards.append(r)
        positions.append(info["position"])
        if term or trunc:
            break
    return np.array(states), np.array(rewards), np.array(positions)


def test_same_seed_same_episode_bit_for_bit(env):
    a = _rollout(env, seed=11)
    other = UavNavEnv(scenario="valley")
    _rollout(other, seed=99)  # a different history must not matter
    b = _rollout(other, seed=11)
    other.close()
    for x, y in zip(a, b, strict=True):
        assert x.shape == y.shape and np.array_equal(x, y)
    c = _rollout(env, seed=12)
    assert not np.array_equal(a[2][:5], c[2][:5])


def test_nan_and_inf_actions_are_rejected_with_a_clear_error(env):
    env.reset(seed=1)
    for bad in ([np.nan, 0, 0, 0], [0, np.inf, 0, 0], [0, 0, -np.inf, 0]):
        with pytest.raises(ValueError, match="finite"):
            env.step(np.array(bad))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3))


def test_out_of_range_actions_are_clipped(env):
    env.reset(seed=2)
    s1, r1, *_ = env.step(np.array([5.0, -7.0, 3.0, 9.0]))
    env.reset(seed=2)
    s2, r2, *_ = env.step(np.array([2.0, -2.0, 2.0, 2.0]))
    assert np.array_equal(s1, s2) and r1 == r2


def test_goal_reached_is_terminal():
    e = UavNavEnv(scenario="valley")
    e.reset(seed=4)
    goal = e.vehicle.truth.position.copy()
    e.reset(seed=4, options={"goal": goal})
    _, _, terminated, truncated, info = e.step(np.zeros(4))
    assert terminated and not truncated
    assert info["goal_reached"] and not info["collision"]
    assert info["distance_to_goal"] <= 2.0
    e.close()


def test_collision_is_terminal_with_collision_reward():
    e = UavNavEnv(scenario="valley")
    e.reset(seed=6)
    # Command a full-speed descent: the terrain is 3.5 m or less below the flight level.
    for _ in range(40):
        _, reward, terminated, truncated, info = e.step(np.array([0.0, 0.0, -2.0, 0.0]))
        if terminated:
            break
    assert terminated and not truncated and info["collision"] and not info["goal_reached"]
    assert reward == e.reward_config.collision
    e.close()


def test_time_limit_is_truncation_not_termination():
    cfg = dataclasses.replace(EnvConfig(), max_steps=4)
    e = UavNavEnv(config=cfg)
    e.reset(seed=8)
    flags = [e.step(np.zeros(4))[2:4] for _ in range(4)]
    assert flags[:3] == [(False, False)] * 3
    assert flags[3] == (False, True)
    e.close()


def test_info_carries_distance_flags_and_reward_components(env):
    env.reset(seed=9)
    _, reward, _, _, info = env.step(np.array([1.0, 0.0, 0.0, 0.0]))
    for key in ("distance_to_goal", "collision", "goal_reached", "reward_components"):
        assert key in info
    parts = info["reward_components"]
    assert set(parts) == {"progress", "altitude", "heading", "velocity_heading"}
    assert reward == pytest.approx(sum(parts.values()))


def test_body_to_world_rotates_by_yaw():
    out = body_to_world(np.array([1.0, 0.0, 0.5, 0.2]), np.pi / 2)
    assert np.allclose(out, [0.0, 1.0, 0.5, 0.2])


def test_rgb_array_render():
    e = UavNavEnv(scenario="valley", render_mode="rgb_array")
    e.reset(seed=1)
    e.step(np.zeros(4))
    frame = e.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8
    assert frame.std() > 5  # not a blank image
    e.close()


def test_the_state_shape_comes_from_the_config_frames_and_radius():
    """``EnvConfig(frames, ico_radius)``: the space, the state and the icosahedron follow
    (the task records them); an observation config of another radius is refused."""
    from perception.observation import ObservationConfig

    env = UavNavEnv(config=EnvConfig(frames=4, ico_radius=3.0))
    try:
        assert env.observation_space.shape == (4, 35) and env.task.frames == 4
        state, _ = env.reset(seed=1)
        assert state.shape == (4, 35) and env.obs_config.radius == env.task.ico_radius == 3.0
    finally:
        env.close()
    with pytest.raises(ValueError, match="ico_radius 3.0"):
        UavNavEnv(config=EnvConfig(ico_radius=3.0), observation_config=ObservationConfig())
