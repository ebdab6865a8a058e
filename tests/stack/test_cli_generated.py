"""Command lines generated from config dataclasses (tyro, ``skyloop.cli.dataclass_cli``):
``skyloop train`` from ``policy.training.settings.TrainConfig``, ``skyloop eval`` from
``policy.training.evaluate.EvalConfig``. The defaults shown and used are the dataclass's, bad
values are one-line errors naming the flag (exit 2) before anything starts, and a
command line gives the config it says."""

from __future__ import annotations

import re
import subprocess
import sys
from dataclasses import MISSING, fields
from pathlib import Path
from typing import get_args

import pytest

from policy.algorithms.agents import ALGOS
from policy.algorithms.rewards import GOAL_REWARDS
from policy.algorithms.td3 import PRECISIONS
from policy.training.evaluate import EvalConfig
from policy.training.settings import ConfigError
from policy.training.train import Algo, Precision, Reward, TrainConfig
from skyloop.cli.dataclass_cli import parse
from skyloop.cli.train import TrainCommand, parse_train

HIDDEN = {"progress", "extra"}  # TrainConfig fields that are not flags


def skyloop(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "skyloop", *args],
                          capture_output=True, text=True, timeout=120)


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def help_entries(text: str) -> dict[str, str]:
    """``--flag`` -> its help text (wrapped rows joined), from tyro's boxed ``--help``."""
    entries: dict[str, str] = {}
    current = None
    for line in text.splitlines():
        row = line.strip().strip("│").rstrip()
        start = re.match(r" (--[a-z0-9-]+)", row)  # an entry starts one space in
        if start:
            current = start.group(1)
            entries[current] = row
        elif current is not None and row.startswith("  "):
            entries[current] += " " + row.strip()
        else:
            current = None
    return entries


def assert_defaults_shown(cls: type, entries: dict[str, str], flags: dict[str, str]) -> None:
    """Each field of ``cls`` but the hidden ones has its flag in ``--help`` with the
    field's default."""
    for f in fields(cls):
        if f.name in HIDDEN:
            assert flag(f.name) not in entries
            continue
        entry = entries[flags.get(f.name, flag(f.name))]
        assert f.default is not MISSING, f.name
        shown = re.search(r"\(default: (.*?)\)$", entry)
        assert shown, entry
        assert shown.group(1) in (str(f.default), repr(f.default)), (f.name, shown.group(1))


def test_help_shows_every_option_with_the_dataclass_default():
    out = skyloop("train", "--help")
    assert out.returncode == 0, out.stderr
    entries = help_entries(out.stdout)
    assert_defaults_shown(TrainConfig, entries, {})
    assert "--algo {td3,ddpg}" in entries["--algo"]  # choices from the Literal types
    assert "{tr,ngr,egr,abr}" in entries["--reward"]
    assert "{auto,fp32,bf16}" in entries["--precision"]
    assert "{off,target}" in entries["--pipeline"]
    assert "(required)" in entries["--out"]
    assert "--no-sync" not in out.stdout and "--no-resume" not in out.stdout


def test_choices_are_the_known_algorithms_rewards_and_precisions():
    assert set(get_args(Algo)) == set(ALGOS)
    assert set(get_args(Reward)) == set(GOAL_REWARDS)
    assert set(get_args(Precision)) == {"auto", *PRECISIONS}


def test_no_flags_give_the_dataclass_defaults():
    command = parse_train(["--out", "run"])
    assert command.config == TrainConfig()
    assert (command.out, command.resume, command.from_logs, command.bc,
            command.init_actor) == (Path("run"), False, None, False, None)


def test_a_command_line_gives_the_config_it_says():
    command = parse_train([
        "--algo", "ddpg", "--reward", "egr", "--scenario", "mix:valley=2,city=1",
        "--world-every", "5", "--episodes", "40", "--seed", "5", "--start-steps", "200",
        "--checkpoint-every", "2", "--threads", "2", "--sync", "--envs", "3",
        "--max-lead", "4", "--device", "cpu", "--precision", "bf16", "--buffer-size", "5000",
        "--lidar-max-range", "5.5", "--out", "runs/x", "--resume"])
    assert command == TrainCommand(out=Path("runs/x"), resume=True, config=TrainConfig(
        algo="ddpg", reward="egr", scenario="mix:valley=2,city=1", world_every=5,
        episodes=40, seed=5, start_steps=200, checkpoint_every=2, threads=2, sync=True,
        envs=3, max_lead=4, device="cpu", precision="bf16", buffer_size=5000,
        lidar_max_range=5.5))
    gym = parse_train(["--env", "Pendulum-v1", "--goal-return", "-200.5", "--out", "g"])
    assert (gym.config.env, gym.config.goal_return) == ("Pendulum-v1", -200.5)
    logs = parse_train(["--from-logs", "a.mcap", "runs/b", "--reward", "tr", "--bc",
                        "--updates", "30", "--init-actor", "actor.pt", "--out", "o"])
    assert logs.from_logs == (Path("a.mcap"), Path("runs/b")) and logs.bc
    assert (logs.updates, logs.init_actor, logs.config.reward) == (30, Path("actor.pt"), "tr")


BAD = [(name, str(least - 1)) for name, least in TrainConfig.AT_LEAST.items()] + [
    ("episodes", "x"), ("envs", "2.5"), ("goal_return", "abc"), ("algo", "ppo"),
    ("reward", "xyz"), ("precision", "fp16"), ("pipeline", "actor"),
    ("updates", "0")]


@pytest.mark.parametrize("name, value", BAD)
def test_a_bad_value_is_one_line_naming_the_flag(capsys, name, value):
    with pytest.raises(SystemExit) as exit_:
        parse_train([flag(name), value, "--out", "unused"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2
    assert err.count("\n") == 1 and err.startswith(f"skyloop train: error: argument "
                                                   f"{flag(name)}: "), err
    assert value in err


def test_bad_command_lines_are_one_line_errors(capsys):
    for argv, message in (([], "the following arguments are required: --out"),
                          (["--out", "o", "--epsiodes", "3"], "unrecognized arguments"),
                          (["--out", "o", "--sync", "yes"], "unrecognized arguments: yes"),
                          (["--out", "o", "--from-logs"], "argument --from-logs: expected"),
                          (["--out", "o", "--episodes"], "argument --episodes: expected")):
        with pytest.raises(SystemExit) as exit_:
            parse_train(argv)
        err = capsys.readouterr().err
        assert exit_.value.code == 2, argv
        assert err.count("\n") == 1 and message in err, (argv, err)


@pytest.mark.parametrize("value", ["-1", "x"])
def test_the_command_refuses_a_bad_count_before_anything_starts(tmp_path, value):
    out = tmp_path / "run"
    proc = skyloop("train", "--episodes", value, "--out", str(out))
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "argument --episodes:" in proc.stderr
    assert "Traceback" not in proc.stderr and not out.exists()


def test_the_config_refuses_a_bad_count_from_python_too():
    with pytest.raises(ConfigError, match="--max-lead: must be at least 1, got 0") as err:
        TrainConfig(max_lead=0)
    assert (err.value.name, err.value.flag) == ("max_lead", "--max-lead")
    config = TrainConfig()
    config.episodes = 0  # changed after construction: validate checks again
    with pytest.raises(ConfigError, match="--episodes"):
        config.validate()


def test_eval_options_come_from_its_dataclass(capsys):
    out = skyloop("eval", "--help")
    assert out.returncode == 0, out.stderr
    assert_defaults_shown(EvalConfig, help_entries(out.stdout), {"json_path": "--json"})
    assert parse_eval([]) == EvalConfig()
    assert parse_eval(["--policy", "scripted", "--scenario", "family:city", "--worlds", "3",
                       "--validation", "--episodes", "4", "--seed", "7", "--json", "e.json"]
                      ) == EvalConfig(policy="scripted", scenario="family:city", worlds=3,
                                      validation=True, episodes=4, seed=7,
                                      json_path=Path("e.json"))
    for argv, says in ((["--episodes", "0"], "argument --episodes: must be at least 1, got 0"),
                       (["--worlds", "0"], "argument --worlds: must be at least 1, got 0"),
                       (["--seed", "x"], "argument --seed: ")):
        with pytest.raises(SystemExit) as exit_:
            parse_eval(argv)
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and err.count("\n") == 1
        assert err.startswith(f"skyloop eval: error: {says}"), err


def parse_eval(argv: list[str]) -> EvalConfig:
    return parse(EvalConfig, argv, prog="skyloop eval", description="")


@pytest.mark.parametrize("args", [["train", "--help"], ["eval", "--help"], ["sim", "--help"],
                                  ["up", "--help"], ["--help"]])
def test_help_into_a_closed_pipe_exits_quietly(args):
    """``skyloop train --help | head -3``: when the reader has gone, no traceback. The
    pipe's read end is closed before the command writes, so every write breaks it (as
    after ``head`` exits), deterministically."""
    import os

    read, write = os.pipe()
    os.close(read)
    try:
        proc = subprocess.run([sys.executable, "-m", "skyloop", *args], stdout=write,
                              stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write)
    assert proc.stderr == "", proc.stderr
    assert proc.returncode in (0, 141), proc.returncode  # 141 = 128 + SIGPIPE, as `yes`


def test_help_piped_into_head_prints_its_lines_and_no_traceback():
    proc = subprocess.run(f"{sys.executable} -m skyloop train --help | head -3", shell=True,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    assert proc.stdout.startswith("usage: skyloop train") and proc.stdout.count("\n") == 3


NO_TORCH = """
import contextlib, io, sys
from skyloop.cli.main import main
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    try:
        main(sys.argv[1:])
    except SystemExit as exit_:
        code = exit_.code
    else:
        code = None
print(code, "torch" in sys.modules)
"""


@pytest.mark.parametrize("args", [["train", "--help"], ["train", "--episodes", "-1", "--out", "o"],
                                  ["eval", "--help"], ["eval", "--episodes", "0"],
                                  ["learner", "--help"], ["health", "--help"]])
def test_help_and_a_bad_command_line_import_no_torch(args):
    """The parse path is light (``TrainConfig``, ``EvalConfig`` in
    ``policy.training.settings``): ``--help`` or a one-line error answers in a fraction of
    a second instead of importing torch, the env and the trainer first."""
    proc = subprocess.run([sys.executable, "-c", NO_TORCH, *args], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    code, torch_imported = proc.stdout.split()
    assert code == ("0" if "--help" in args else "2"), proc.stdout
    assert torch_imported == "False", f"skyloop {' '.join(args)} imported torch"
