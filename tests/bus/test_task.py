"""The task specification (bus.task): outcome rules, serialisation, and that the parts
built from it agree with it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from bus.task import TASK, TaskSpec, episode_outcome


@pytest.mark.parametrize("collided,distance,altitude,steps,expected", [
    (True, 0.5, 3.0, 10, "collision"),  # a collision wins over a reached goal
    (False, 2.0, 6.0, 10, "success"),  # on the radius and the altitude limit
    (False, 1.0, 6.5, 10, "None"),  # above the goal altitude: not yet
    (False, 2.01, 3.0, 299, "None"),
    (False, 2.01, 3.0, 300, "timeout"),
    (False, 1.0, 3.0, 300, "success"),  # success on the last step is success
])
def test_outcome_rules(collided, distance, altitude, steps, expected):
    assert str(TASK.outcome(collided, distance, altitude, steps)) == expected


def test_limits_are_the_spec_fields():
    task = replace(TASK, max_steps=4, goal_radius=5.0)
    assert task.outcome(False, 4.5, 3.0, 3) == "success"
    assert task.outcome(False, 9.0, 3.0, 4) == "timeout"
    assert TASK.obs_dim == 35 and TASK.state_shape == (3, 35) and TASK.state_dim == 105


def test_episode_outcome():
    assert episode_outcome(True, False) == "success"
    assert episode_outcome(False, True) == "collision"
    assert episode_outcome(False, False) == "timeout"


def test_round_trip_and_bad_fields():
    spec = replace(TASK, frames=4, max_action=1.5)
    assert TaskSpec.from_dict(spec.to_dict()) == spec
    with pytest.raises(ValueError, match="actor.pt: unknown task field 'fps'"):
        TaskSpec.from_dict({"fps": 3}, where="actor.pt")
    with pytest.raises(ValueError, match="task field 'frames' must be a number"):
        TaskSpec.from_dict({"frames": "3"})
    with pytest.raises(ValueError, match="task field 'frames' must be an integer"):
        TaskSpec.from_dict({"frames": 3.7})


def test_env_networks_and_replay_take_their_sizes_from_the_spec():
    from policy.algorithms.replay import ReplayBuffer
    from policy.algorithms.td3 import TD3Config
    from policy.training.env import UavNavEnv

    env = UavNavEnv(scenario="valley")
    try:
        assert env.observation_space.shape == TASK.state_shape
        assert env.action_space.shape == (TASK.action_dim,)
        assert float(env.action_space.high[0]) == TASK.max_action
        state, _ = env.reset(seed=1)
        assert state.shape == TASK.state_shape and state.dtype == np.float32
    finally:
        env.close()
    cfg = TD3Config()
    assert (cfg.state_dim, cfg.action_dim, cfg.max_action) == (
        TASK.state_dim, TASK.action_dim, TASK.max_action)
    assert ReplayBuffer(10).state_shape == TASK.state_shape


def test_parameters_hold_the_only_defaults_and_set_the_fields_they_name():
    from bus import params
    from perception.observation import ObservationConfig
    from sitl.commander.types import CommanderConfig
    from sitl.episode import EpisodeSim
    from sitl.flight.vehicle import VehicleConfig

    cfg, vehicle, sim = CommanderConfig(), VehicleConfig(), EpisodeSim()
    owners = {"commander": cfg, "autopilot": vehicle, "observation": ObservationConfig(),
              "lidar": sim}
    for p in params.PARAMS:
        assert p.sets, p.name  # every parameter says what it sets
        for target in p.sets:  # ... and that field's default is the parameter's
            owner, attribute = target.split(".")
            assert getattr(owners[owner], attribute) == p.default, target
        if p.task_field:
            assert getattr(TASK, p.task_field) == p.default
    assert params.bind("MPC_XY_VEL_MAX", 3.0, {"commander": cfg, "autopilot": None})
    assert cfg.rtl_speed == 3.0
    assert not params.bind("SKY_ICO_RADIUS", 5.0, {"commander": cfg, "autopilot": None})
    assert params.bind("SKY_ICO_RADIUS", 6.0, {"commander": cfg, "lidar": sim})
    assert sim.ico_radius == 6.0 and sim.lidar.config.max_range == 6.5


def test_the_lidar_reaches_the_radius_the_observation_is_made_at():
    """SKY_ICO_RADIUS set on the sim (``EpisodeSim.ico_radius``) gives the LiDAR the range
    a policy trained at that radius was trained with (``--lidar-max-range 6.5`` for 6 m):
    the next scan is the very scan of a sim built with that range (same episode, same
    noise stream), its returns reach past 4.5 m, and worlds built later get it too."""
    import numpy as np

    from sitl.episode import EpisodeConfig, EpisodeSim

    sim, trained = EpisodeSim(), EpisodeSim(EpisodeConfig(lidar_max_range=6.5))
    sim.reset(np.random.default_rng(3))
    near = np.linalg.norm(sim.scan(), axis=1)
    assert near.max() <= 4.5 + 1e-6
    sim.reset(np.random.default_rng(3))  # the episode again (the noise stream restarts)
    trained.reset(np.random.default_rng(3))
    sim.ico_radius = 6.0  # between reset and the first scan: the stream is kept
    far = sim.scan()
    np.testing.assert_array_equal(far, trained.scan())
    assert 4.5 < np.linalg.norm(far, axis=1).max() <= 6.5 + 1e-6
    sim.use_world("city")  # a world built after the change
    assert sim.lidar.config.max_range == 6.5


def test_off_task_names_parameters_the_policy_was_not_trained_under():
    from bus import params

    assert params.off_task(TASK, "MPC_XY_VEL_MAX", 2.0) is None
    assert params.off_task(TASK, "GF_MAX_HOR_DIST", 5.0) is None  # no task field
    assert params.off_task(TASK, "MPC_Z_VEL_MAX", 1.5) == "MPC_Z_VEL_MAX=1.5 m/s, trained with 2"
    slow = TaskSpec(max_speed_xy=1.0)
    assert params.off_task(slow, "MPC_XY_VEL_MAX", 1.0) is None
    assert "trained with 1" in params.off_task(slow, "MPC_XY_VEL_MAX", 2.0)
