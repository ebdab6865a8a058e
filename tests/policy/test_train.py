"""Training runs: seeded, checkpointed, resumable; bad input gives clear errors."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from policy.training.plots import curve_figure
from policy.training.train import CHECKPOINT, TrainConfig, Trainer

SMALL = dict(scenario="valley", seed=3, start_steps=60, buffer_size=5000, checkpoint_every=2,
             sync=True)


def _train(out: Path, episodes: int, resume: bool = False, **kw) -> str:
    cfg = TrainConfig(episodes=episodes, **{**SMALL, **kw})
    Trainer(cfg, out).run(resume=resume)
    return (out / "episodes.csv").read_text()


def test_same_seed_same_csv_and_resume_continues_exactly(tmp_path):
    full = _train(tmp_path / "a", 5)
    assert full == _train(tmp_path / "b", 5)  # same seed, same CSV
    assert len(full.splitlines()) == 1 + 5
    # Stop after 3 episodes (checkpoint at 2 and at the end), then pretend the process
    # died after episode 2: roll the directory back to the episode-2 checkpoint state.
    part = tmp_path / "c"
    _train(part, 2)
    ckpt_at_2 = (part / CHECKPOINT).read_bytes()
    _train(part, 3, resume=True)
    (part / CHECKPOINT).write_bytes(ckpt_at_2)  # the run "died" before checkpointing 3
    resumed = _train(part, 5, resume=True)
    assert resumed == full
    assert (part / "curve.png").stat().st_size > 1000


def _scalars(acc, tag: str) -> list[tuple[int, float]]:
    return [(e.step, e.value) for e in acc.Scalars(tag)]


def test_tensorboard_two_axes_actor_loss_hparams_and_the_curve(tmp_path):
    """Scalars against episodes (tb) and env steps (tb/env_steps), the actor loss, steps/s
    and the hparams with the success rate as metric; the curve's title, panels, ticks."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.plugins.hparams import plugin_data_pb2

    out = tmp_path / "run"
    kw = {**SMALL, "start_steps": 20}
    Trainer(TrainConfig(episodes=2, **kw), out).run()  # checkpoint at episode 2
    ckpt_at_2 = (out / CHECKPOINT).read_bytes()
    Trainer(TrainConfig(episodes=3, **kw), out).run(resume=True)
    (out / CHECKPOINT).write_bytes(ckpt_at_2)  # episode 3 is orphaned: "died" before its
    summary = Trainer(TrainConfig(episodes=4, **kw), out).run(resume=True)  # checkpoint
    with (out / "episodes.csv").open(newline="") as f:
        total_steps = [int(r["total_steps"]) for r in csv.DictReader(f)]
    assert total_steps[-1] == summary["total_steps"] > kw["start_steps"] + 2

    by_episode = EventAccumulator(str(out / "tb")).Reload()
    tags = set(by_episode.Tags()["scalars"])
    assert {"episode/return", "episode/success_rate_500", "loss/critic_loss",
            "loss/actor_loss", "time/env_steps_per_s", "time/env_steps"} <= tags
    # each axis purged after its checkpoint, and only there: one point per episode
    assert [s for s, _ in _scalars(by_episode, "episode/return")] == [1, 2, 3, 4]
    assert all(v > 0 for _, v in _scalars(by_episode, "time/env_steps_per_s"))
    # the actor's loss at every episode end after the first delayed update, as the critic's
    assert len(_scalars(by_episode, "loss/actor_loss")) == len(
        _scalars(by_episode, "loss/critic_loss")) > 0
    assert _scalars(by_episode, "episode/success_rate_500")[-1][1] == pytest.approx(
        summary["success_rate_500"])

    by_steps = EventAccumulator(str(out / "tb" / "env_steps")).Reload()
    assert {"env_steps/return", "env_steps/success_rate_500", "env_steps/actor_loss",
            "env_steps/steps_per_s", "env_steps/episodes"} <= set(by_steps.Tags()["scalars"])
    assert [s for s, _ in _scalars(by_steps, "env_steps/episodes")] == total_steps
    assert [v for _, v in _scalars(by_steps, "env_steps/episodes")] == [1, 2, 3, 4]

    hp = {tag: plugin_data_pb2.HParamsPluginData.FromString(content)
          for tag, content in by_episode.PluginTagToContent("hparams").items()}
    start = hp["_hparams_/session_start_info"].session_start_info.hparams
    assert start["algo"].string_value == "td3" and start["reward"].string_value == "abr"
    assert start["task"].string_value == "valley" and start["seed"].number_value == 3
    assert start["lr"].number_value > 0 and start["hidden"].string_value == "400x300"
    metrics = hp["_hparams_/experiment"].experiment.metric_infos
    assert [m.name.tag for m in metrics] == ["episode/success_rate_500"]
    assert "_hparams_/session_end_info" in hp  # the run finished

    fig = curve_figure([out])
    assert fig._suptitle.get_text() == "TD3 + ABR on valley, seed 3"
    assert [ax.get_xlabel() for ax in fig.axes] == ["episode"] * 3
    assert "return" in fig.axes[2].get_ylabel()
    fig.canvas.draw()
    ticks = [t for t in fig.axes[0].get_xticks() if 1 <= t <= 4]
    assert ticks and all(float(t).is_integer() for t in ticks)


def _children(pid: int) -> list[int]:
    return [int(c) for t in Path(f"/proc/{pid}/task").iterdir()
            for c in (t / "children").read_text().split()]


def test_killed_run_resumes_from_last_checkpoint(tmp_path):
    """The parallel mode (collector process + learner) SIGKILLed: its collector dies with
    it, and --resume continues the episodes without a gap. (--sync runs: resumed to the
    same CSV in test_same_seed_same_csv_and_resume_continues_exactly, and SIGKILLed in a
    grid in tests/experiment/test_experiment.py.)"""
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "skyloop", "train", "--episodes", "40", "--seed", "5",
           "--start-steps", "200", "--checkpoint-every", "2", "--out", str(out), "--envs", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while not (out / CHECKPOINT).exists() and time.time() < deadline:
        time.sleep(0.2)
    time.sleep(0.5)
    children = _children(proc.pid)  # the parallel mode's collector
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    for child in children:  # dies with the learner
        deadline = time.time() + 10
        while Path(f"/proc/{child}").exists() and "Z" not in _state(child):
            assert time.time() < deadline, f"process {child} outlived the killed trainer"
            time.sleep(0.1)
    state = torch.load(out / CHECKPOINT, weights_only=False)
    done = state["episode"]
    assert 2 <= done < 40
    rc = subprocess.run([*cmd[:5], str(done + 2), *cmd[6:], "--resume"],  # an episode per env
                        capture_output=True, text=True, timeout=300)
    assert rc.returncode == 0, rc.stderr[-2000:]
    rows = (out / "episodes.csv").read_text().splitlines()
    episodes = [int(r.split(",")[0]) for r in rows[1:]]
    assert episodes == list(range(1, len(episodes) + 1))  # no gap, no duplicate
    final = torch.load(out / CHECKPOINT, weights_only=False)
    assert final["episode"] == len(episodes) and final["total_steps"] > state["total_steps"]


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "Z"


@pytest.mark.parametrize("pipeline", ["target", "off"])
def test_parallel_mode_keeps_one_update_per_env_step(tmp_path, pipeline):
    """Collector process and learner (in each of its thread layouts): every episode is
    recorded once, in order, and the learner's updates trail the env steps by at most the
    collector's bounded lead."""
    cfg = TrainConfig(episodes=6, **{**SMALL, "sync": False, "envs": 2, "max_lead": 4,
                                     "precision": "bf16", "pipeline": pipeline})
    assert Trainer(cfg, tmp_path).run()["precision"] == "bf16"
    rows = (tmp_path / "episodes.csv").read_text().splitlines()[1:]
    assert [int(r.split(",")[0]) for r in rows] == list(range(1, 7))
    state = torch.load(tmp_path / CHECKPOINT, weights_only=False)
    due = state["total_steps"] - cfg.start_steps + 1
    assert 0 <= due - state["agent"]["updates"] <= cfg.max_lead + cfg.envs
    assert sum(int(r.split(",")[2]) for r in rows) <= state["total_steps"]


def test_a_collector_whose_learner_died_while_it_started_ends_at_once(tmp_path):
    """The learner may die before the collector's parent-death signal is set (the spawn
    takes a second of imports): the collector sees it is not the learner's child and
    ends before building anything."""
    import functools

    import torch.multiprocessing as tmp

    from policy.training.collector import CollectorSpec, collector_main

    marker = tmp_path / "envs-built"
    ctx = tmp.get_context("spawn")
    spec = CollectorSpec(make_envs=functools.partial(Path.touch, marker), envs=1,
                         actor_kwargs={}, exploration_noise=0.2, seed=0, max_action=2.0,
                         action_dim=4, start_steps=0, next_episode=0, steps=0, max_lead=1,
                         learner_pid=1)  # not its parent: as if the learner were gone
    recv, send = ctx.Pipe(duplex=False)
    stop = ctx.Event()  # referenced until the child has it
    proc = ctx.Process(target=collector_main, args=(send, spec, None, stop, abs))
    proc.start()
    send.close()
    proc.join(timeout=60)
    assert proc.exitcode == 0
    assert not marker.exists()
    with pytest.raises(EOFError):
        recv.recv()


def test_parallel_mode_draws_the_random_phase_as_sync_does(tmp_path):
    """Before the first update both loops take the same actions on the same episodes."""
    kw = {"start_steps": 100_000}
    assert _train(tmp_path / "p", 3, sync=False, **kw) == _train(tmp_path / "s", 3, **kw)


def test_auto_precision_takes_what_the_device_has_and_says_so(tmp_path):
    from policy.algorithms.td3 import best_precision

    assert TrainConfig().precision == "auto"
    summary = Trainer(TrainConfig(episodes=1, **SMALL), tmp_path).run()
    assert summary["precision"] == best_precision("cpu")
    state = torch.load(tmp_path / CHECKPOINT, weights_only=False)
    assert state["config"]["precision"] == "auto"
    assert state["agent"]["config"]["precision"] == best_precision("cpu")


def test_a_resumed_run_keeps_the_precision_it_began_with(tmp_path):
    """--precision auto resumes in the checkpoint's arithmetic, exactly; an explicit
    other precision is a clear error."""
    full = _train(tmp_path / "full", 3, precision="fp32")
    _train(tmp_path / "cut", 2, precision="fp32")
    assert _train(tmp_path / "cut", 3, resume=True, precision="auto") == full
    state = torch.load(tmp_path / "cut" / CHECKPOINT, weights_only=False)
    assert state["agent"]["config"]["precision"] == "fp32"
    with pytest.raises(ValueError, match="trained with --precision fp32, this run asks "
                                         "for bf16"):
        _train(tmp_path / "cut", 4, resume=True, precision="bf16")


def test_mixed_precision_sync_runs_are_reproducible(tmp_path):
    a = _train(tmp_path / "a", 3, precision="bf16")
    assert a == _train(tmp_path / "b", 3, precision="bf16")
    assert a != _train(tmp_path / "c", 3, precision="fp32")  # and not the float32 run
    state = torch.load(tmp_path / "a" / CHECKPOINT, weights_only=False)
    assert state["agent"]["config"]["precision"] == "bf16" and state["agent"]["updates"] > 0


def test_sync_envs_keep_their_episodes_apart(tmp_path):
    """Two envs stepped in turn: each episode's rewards are rewritten on its own range,
    and the run is reproducible."""
    a = _train(tmp_path / "a", 4, envs=2)
    assert a == _train(tmp_path / "b", 4, envs=2)
    steps = [int(r.split(",")[2]) for r in a.splitlines()[1:]]
    assert len(steps) == 4 and all(1 <= s <= 300 for s in steps)


def test_bad_input_is_a_clear_error_and_overwrites_nothing(tmp_path):
    with pytest.raises(ValueError, match="unknown algorithm"):
        TrainConfig(algo="ppo").validate()
    with pytest.raises(ValueError, match="unknown reward"):
        TrainConfig(reward="xyz").validate()
    with pytest.raises(ValueError, match="unknown scenario"):
        TrainConfig(scenario="moon").validate()
    with pytest.raises(ValueError, match="--envs"):
        TrainConfig(envs=0).validate()
    with pytest.raises(ValueError, match="--precision"):
        TrainConfig(precision="fp16").validate()
    with pytest.raises(ValueError, match=r"--pipeline: must be one of \['off', 'target'\]"):
        TrainConfig(pipeline="actor").validate()  # a grid file of before it was removed
    with pytest.raises(ValueError, match="--device 'cuda:7'"):
        TrainConfig(device="cuda:7").validate()

    out = tmp_path / "run"
    _train(out, 2)
    before = (out / "episodes.csv").read_text()
    with pytest.raises(FileExistsError, match="--resume"):
        _train(out, 3)
    with pytest.raises(ValueError, match="reward"):
        _train(out, 3, resume=True, reward="tr")  # checkpoint of an ABR run
    (out / CHECKPOINT).write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable"):
        _train(out, 3, resume=True)
    assert (out / "episodes.csv").read_text() == before
    with pytest.raises(FileNotFoundError, match="nothing to resume"):
        _train(tmp_path / "empty", 3, resume=True)


def test_cli_reports_bad_arguments_without_traceback():
    out = subprocess.run([sys.executable, "-m", "skyloop", "train", "--algo", "ppo",
                          "--out", "unused"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert "argument --algo: invalid choice: 'ppo'" in out.stderr
    assert "Traceback" not in out.stderr



@pytest.mark.parametrize("sync", [True, False])
def test_mixture_runs_log_each_world_and_keep_snapshots(tmp_path, sync):
    """A mixture run's CSV names the world each episode flew: the one the episode's seed
    draws (``WorldSource.draw`` is the first thing a reset draws); ``--snapshot-every``
    keeps the actor of every N-th episode, loadable by ``skyloop eval``."""
    import numpy as np

    from policy.training.evaluate import ActorController
    from policy.training.train import episode_seed
    from sitl.world.families import WorldSource

    spec = "mix:valley,forest,city,dynamic"
    _train(tmp_path, 4, scenario=spec, snapshot_every=2, sync=sync)
    with (tmp_path / "episodes.csv").open() as f:
        worlds = [row["world"] for row in csv.DictReader(f)]
    source = WorldSource.parse(spec)
    assert worlds == [source.draw(np.random.default_rng(episode_seed(SMALL["seed"], i)))
                      for i in range(4)]
    kept = sorted(p.name for p in (tmp_path / "snapshots").iterdir())
    assert kept == ["actor-ep2.pt", "actor-ep4.pt"]
    ActorController(tmp_path / "snapshots" / "actor-ep2.pt")  # a whole actor file


def test_a_run_resumed_with_an_older_csv_keeps_its_columns(tmp_path):
    """Resuming a run whose CSV predates a column appends rows in the file's own columns
    (no row wider than its header)."""
    _train(tmp_path, 2)
    path = tmp_path / "episodes.csv"
    rows = list(csv.reader(path.open(newline="")))
    old = [r[:-1] for r in rows]  # as written before the world column existed
    with path.open("w", newline="") as f:
        csv.writer(f).writerows(old)
    _train(tmp_path, 4, resume=True)
    rows = list(csv.reader(path.open(newline="")))
    assert rows[0] == old[0] and len(rows) == 5
    assert {len(r) for r in rows} == {len(old[0])}


def test_frames_radius_and_encoding_shape_the_state_and_travel_with_the_actor(tmp_path):
    """``--frames 2 --ico-radius 3 --encoding proximity``: the networks read 2 x 35
    values, ABR groups 2 steps, the actor file records all three, the default task refuses
    it by name, ``evaluate`` flies it in the state it was trained on (not the default's),
    and a resume that asks for another state is refused naming the field."""
    from bus.task import TASK
    from policy.algorithms.td3 import load_actor
    from policy.training.evaluate import evaluate, format_summary

    trainer = Trainer(TrainConfig(episodes=2, frames=2, ico_radius=3.0, encoding="proximity",
                                  **SMALL), tmp_path)
    trainer.run()
    assert trainer.agent.actor.net[0].in_features == 2 * TASK.obs_dim
    assert trainer.goal_reward.config.p_frames == 2
    actor = load_actor(tmp_path / "actor.pt")
    assert (actor.trained_task.frames, actor.trained_task.ico_radius) == (2, 3.0)
    assert actor.trained_observation["encoding"] == "proximity"
    assert actor.trained_observation["radius"] == 3.0
    with pytest.raises(ValueError, match="trained for task frames=2, but this task has "
                                         "frames=3"):
        load_actor(tmp_path / "actor.pt", task=TASK)
    summary = evaluate(str(tmp_path / "actor.pt"), "valley", episodes=2, progress=False)
    assert summary["task"] == {"frames": 2, "ico_radius": 3.0, "encoding": "proximity"}
    assert summary["episodes"] == 2
    assert ("its state: 2 frames, icosahedron radius 3 m, proximity encoding"
            in format_summary(summary))
    for other in ({"frames": 3}, {"ico_radius": 4.0}, {"encoding": "distance"}):
        cfg = TrainConfig(episodes=3, **{**SMALL, "frames": 2, "ico_radius": 3.0,
                                         "encoding": "proximity", **other})
        with pytest.raises(ValueError, match=f"checkpoint has {next(iter(other))}="):
            Trainer(cfg, tmp_path).run(resume=True)


@pytest.mark.parametrize(("kw", "flag"), [
    ({"frames": 1}, "--frames"), ({"ico_radius": 0.2}, "--ico-radius"),
    ({"encoding": "binary"}, "--encoding: must be one of"),
    ({"env": "Pendulum-v1", "frames": 5}, "--frames: is for the skyloop task"),
    ({"ico_radius": float("nan")}, "--ico-radius"),
    ({"ico_radius": 6.0}, "--ico-radius: 6.0 m is beyond the LiDAR's range")])
def test_a_state_shape_the_task_cannot_have_is_refused_naming_the_flag(kw, flag):
    with pytest.raises(ValueError, match=flag):
        TrainConfig(**kw)
    assert TrainConfig(ico_radius=6.0, lidar_max_range=6.5).ico_radius == 6.0
