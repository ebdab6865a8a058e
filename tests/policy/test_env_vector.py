"""The env outside skyloop's own code: a fresh interpreter, Stable-Baselines3's
SubprocVecEnv and Gymnasium's async vector env, whose workers never import skyloop
themselves; the spec's episode limit."""

from __future__ import annotations

import subprocess
import sys

import gymnasium
import numpy as np
import pytest

import skyloop
from bus.task import TASK

QUALIFIED_ID = f"skyloop:{skyloop.ENV_ID}"  # Gymnasium imports skyloop before the lookup
KW = {"scenario": "valley", "lidar_max_range": 4.5}  # the cheapest: truncated LiDAR


def test_fresh_interpreter_makes_the_env_from_the_qualified_id():
    code = (
        "import sys, gymnasium\n"
        "assert 'skyloop' not in sys.modules\n"
        f"env = gymnasium.make({QUALIFIED_ID!r})\n"
        "state, _ = env.reset(seed=0)\n"
        "env.step(env.action_space.sample())\n"
        "import skyloop  # already registered: no second registration, no warning\n"
        "print(env.spec.id, env.spec.max_episode_steps, state.shape)\n"
    )
    # -W error: an "Overriding environment" warning (double registration) would fail it
    out = subprocess.run([sys.executable, "-W", "error", "-c", code], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == [skyloop.ENV_ID, str(TASK.max_steps), "(3,", "35)"]


def test_spec_carries_the_task_episode_limit():
    spec = gymnasium.spec(skyloop.ENV_ID)
    assert spec.max_episode_steps == TASK.max_steps
    env = gymnasium.make(skyloop.ENV_ID, **KW)
    assert isinstance(env, gymnasium.wrappers.TimeLimit)
    assert env.unwrapped.config.max_steps == spec.max_episode_steps  # they agree
    env.close()


def _reset_and_step(venv_reset, venv_step, action_space, n):
    obs = venv_reset()
    assert obs.shape == (n, *TASK.state_shape) and obs.dtype == np.float32
    actions = np.stack([action_space.sample() for _ in range(n)])
    for _ in range(3):
        out = venv_step(actions)
    assert out[0].shape == (n, *TASK.state_shape)
    assert np.all(np.isfinite(out[1]))


def test_stable_baselines3_subproc_vec_env():
    sb3 = pytest.importorskip("stable_baselines3", reason="pip install -e '.[test]'")
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    # the workers start from SB3's forkserver, where skyloop was never imported
    venv = make_vec_env(QUALIFIED_ID, n_envs=2, seed=0, vec_env_cls=SubprocVecEnv,
                        env_kwargs=KW)
    try:
        assert isinstance(venv, SubprocVecEnv), sb3.__version__
        _reset_and_step(venv.reset, venv.step, venv.action_space, 2)
        assert venv.get_attr("spec")[0].max_episode_steps == TASK.max_steps
    finally:
        venv.close()


def test_gymnasium_async_vector_env():
    # spawned workers: the spec (entry point policy.training.env:UavNavEnv) travels to them, so
    # they need not import skyloop either
    venv = gymnasium.make_vec(skyloop.ENV_ID, num_envs=2, vectorization_mode="async",
                              vector_kwargs={"context": "spawn"}, **KW)
    try:
        assert isinstance(venv, gymnasium.vector.AsyncVectorEnv)
        _reset_and_step(lambda: venv.reset(seed=0)[0], venv.step,
                        venv.single_action_space, 2)
    finally:
        venv.close()
