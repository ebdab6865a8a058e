"""Worlds drawn per episode (sitl.world.families): family and mixture specs, world variants,
seeded draws, disjoint seed ranges, evaluation on held-out worlds."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from loopback import up_args

from policy.training.env import UavNavEnv
from sitl.world.families import (
    EVAL_SEED0,
    TRAIN_SEEDS,
    VALIDATION_SEED0,
    WorldSource,
    check_scenario,
    eval_worlds,
)
from sitl.world.scenario import ScenarioError, load_scenario
from sitl.world.world import World

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("spec,says", [
    ("mix:", "needs family names"), ("family:", "needs one family name"),
    ("family:moon", "unknown family 'moon'"), ("family:city,forest", "one family name"),
    ("mix:valley=0", "must be > 0"), ("mix:city=x", "must be a number"),
    ("mix:city=nan", "must be > 0"),
])
def test_bad_specs_name_what_is_wrong(spec, says):
    with pytest.raises(ScenarioError, match=says):
        WorldSource.parse(spec)


def test_specs_parse():
    assert WorldSource.parse("valley").fixed and WorldSource.parse("city#5").fixed
    m = WorldSource.parse("mix:valley=3,city")
    assert m.families == ("valley", "city") and m.weights == (3.0, 1.0)
    assert WorldSource.parse("family:forest").families == ("forest",)
    with pytest.raises(ScenarioError, match="integer"):
        load_scenario("city#abc")
    with pytest.raises(ScenarioError, match="unknown scenario 'moon'"):
        check_scenario("moon#3")


def test_a_world_seed_gives_new_geometry_and_aircraft_loops():
    base, a, b = (World(load_scenario(n)) for n in ("dynamic", "dynamic#1", "dynamic#2"))
    heights = [w.terrain.heights for w in (base, a, b)]
    assert not np.array_equal(heights[0], heights[1])
    assert not np.array_equal(heights[1], heights[2])
    again = World(load_scenario("dynamic#1"))  # the name is the world
    assert np.array_equal(again.terrain.heights, heights[1])
    assert np.array_equal(again.fleet.waypoints, a.fleet.waypoints)
    assert not np.allclose(a.fleet.waypoints, base.fleet.waypoints)
    # the loops keep their shape (turned about the centre, maybe mirrored)
    r = [np.linalg.norm(w.fleet.waypoints[..., :2], axis=-1) for w in (base, a)]
    assert np.allclose(np.sort(r[0].ravel()), np.sort(r[1].ravel()))
    city = [World(load_scenario(n)) for n in ("city#1", "city#2")]
    assert [s.box[:2].tolist() for s in city[0].solids] != \
        [s.box[:2].tolist() for s in city[1].solids]


def test_the_episode_seed_fixes_the_world_and_the_episode():
    env = UavNavEnv(scenario="mix:valley,forest,city,dynamic")
    seen = {}
    for seed in (3, 4, 3, 5, 4):
        env.reset(seed=seed)
        got = (env.sim.world_name, env.sim.start.tolist(), env.sim.goal.tolist())
        assert seen.setdefault(seed, got) == got
        assert env.world is env.sim.world and env.lidar is env.sim.lidar
    names = {v[0] for v in seen.values()}
    assert len(names) == 3  # three seeds, three worlds
    for name in names:
        family, _, world_seed = name.rpartition("#")
        assert family in ("valley", "forest", "city", "dynamic")
        assert TRAIN_SEEDS[0] <= int(world_seed) < TRAIN_SEEDS[1]


def test_mixture_weights_and_world_every():
    src = WorldSource.parse("mix:valley=9,city=1")
    rng = np.random.default_rng(0)
    fams = [src.draw(rng).partition("#")[0] for _ in range(400)]
    assert 0.85 < fams.count("valley") / 400 < 0.95
    env = UavNavEnv(scenario="family:forest", world_every=3)
    names = []
    for seed in range(7):
        env.reset(seed=seed)
        names.append(env.sim.world_name)
    assert names[0] == names[1] == names[2] != names[3] == names[4] == names[5] != names[6]
    assert env.sim.world_builds == 1 + 3  # the template, then three drawn worlds


def test_held_out_and_validation_worlds_are_never_trained_on():
    assert TRAIN_SEEDS[1] <= VALIDATION_SEED0 < EVAL_SEED0
    held, val = eval_worlds("city", 200), eval_worlds("city", 200, validation=True)
    assert not set(held) & set(val)
    assert all(int(n.rpartition("#")[2]) >= TRAIN_SEEDS[1] for n in held + val)


def test_eval_flies_held_out_worlds_of_a_family(tmp_path):
    out = tmp_path / "eval.json"
    proc = subprocess.run([sys.executable, "-m", "skyloop", "eval", "--policy", "scripted",
                           "--scenario", "family:city", "--worlds", "3", "--episodes", "4",
                           "--json", str(out)], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert f"3 held-out worlds, seeds {EVAL_SEED0}-{EVAL_SEED0 + 2}" in proc.stdout
    for bad, says in ((["--scenario", "family:city"], "give --worlds N"),
                      (["--scenario", "valley", "--worlds", "2"], "--worlds needs")):
        proc = subprocess.run([sys.executable, "-m", "skyloop", "eval", "--policy", "scripted",
                               "--episodes", "1", *bad], cwd=ROOT, capture_output=True,
                              text=True, timeout=120)
        assert proc.returncode == 2 and says in proc.stderr, proc.stderr
    from policy.training.evaluate import evaluate  # as the experiment scripts call it

    with pytest.raises(ValueError, match="--worlds: expected a positive integer, got 0"):
        evaluate("scripted", "family:city", 1, worlds=0)


def test_the_stack_flies_the_drawn_world_and_logs_its_name(tmp_path):
    """``skyloop up --scenario family:city``: the sim draws each episode's world as the
    env does (same seed, same world, same start), and the log's START names it, so the
    log can be rebuilt (``load_scenario(NAME#SEED)``)."""
    from bus.log.reader import read_episodes

    proc = subprocess.run(up_args("--scenario", "family:city", "--episodes", "2",
                                  "--max-steps", "15", "--policy", "scripted",
                                  "--log-dir", str(tmp_path)), cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    [run] = list(tmp_path.glob("run-*"))
    episodes, _ = read_episodes(run)
    env = UavNavEnv(scenario="family:city")
    assert len(episodes) == 2
    for ep in episodes:
        start = ep.topic("episode")[0].decode()
        env.reset(seed=int(start.seed))
        assert start.scenario == env.sim.world_name and start.scenario.startswith("city#")
        assert np.allclose([start.start.x, start.start.y], env.sim.start[:2])
