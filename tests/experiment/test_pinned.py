"""experiments/pinned.sh: a grid's finished trials come home without checkpoints, and bad
arguments are one line with exit 2. The script runs in a small git repository of its own
(a copy of the script, one commit) beside a worktree directory laid out as a running grid
leaves it; `start` is exercised only on its refusals (it builds a venv and runs a grid), and
`queue` on its refusals and its wait for a running grid (the grid it then starts fails at
once: the small repository has no Makefile to build a venv with)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
import uuid
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "pinned.sh"


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True,
                          text=True).stdout.strip()


def repo_with_script(tmp_path: Path) -> tuple[Path, str]:
    main = tmp_path / "main"
    (main / "experiments").mkdir(parents=True)
    shutil.copy(SCRIPT, main / "experiments" / "pinned.sh")
    (main / "experiments" / "g.toml").write_text('name = "g"\n')
    git(main, "init", "-q")
    git(main, "add", ".")
    git(main, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "script")
    return main, git(main, "rev-parse", "--short=7", "HEAD")


def pinned(main: Path, *args: str, env: dict[str, str] | None = None
           ) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "experiments/pinned.sh", *args], cwd=main,
                          capture_output=True, text=True, timeout=60,
                          env={**os.environ, **(env or {})})


def wait_for(check, timeout: float = 20.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if check():
            return True
        time.sleep(0.1)
    return False


def test_collect_copies_finished_trials_without_checkpoints(tmp_path):
    main, sha = repo_with_script(tmp_path)
    grid = tmp_path / f"exp-{sha}" / "experiments" / "g"
    done, running = grid / "valley-td3+abr-s0", grid / "valley-td3+tr-s0"
    for trial in (done, running):
        (trial / "tb").mkdir(parents=True)
        (trial / "tb" / "events.out").write_text("tb")
        (trial / "episodes.csv").write_text("episode,outcome\n1,success\n")
        (trial / "checkpoint.pt").write_bytes(b"\0" * 64)
    (done / "result.json").write_text("{}")
    (done / "actor.pt").write_bytes(b"actor")
    (grid / "runs.json").write_text("[]")
    (grid / "grid.toml").write_text('name = "g"\n')

    r = pinned(main, "collect", "HEAD", "experiments/g/")
    assert r.returncode == 0, r.stderr
    assert "1 finished trial(s)" in r.stdout
    home = main / "experiments" / "g"
    got = sorted(str(p.relative_to(home)) for p in home.rglob("*") if p.is_file())
    assert got == ["grid.toml", "runs.json", "valley-td3+abr-s0/actor.pt",
                   "valley-td3+abr-s0/episodes.csv", "valley-td3+abr-s0/result.json"]
    # a file main has newer (validation appended to it since) survives a second collect;
    # one the worktree has newer is brought home
    log = home / "valley-td3+abr-s0" / "selection.jsonl"
    (done / "selection.jsonl").write_text("row 1\n")
    (done / "actor.pt").write_bytes(b"actor, later")
    os.utime(done / "selection.jsonl", (time.time() - 60, time.time() - 60))
    os.utime(done / "actor.pt", (time.time() + 60, time.time() + 60))  # tar: 1-s times
    log.write_text("row 1\nrow 2\n")
    r = pinned(main, "collect", "HEAD", "experiments/g/")
    assert r.returncode == 0, r.stderr
    assert log.read_text() == "row 1\nrow 2\n"
    assert (home / "valley-td3+abr-s0" / "actor.pt").read_bytes() == b"actor, later"


def test_bad_arguments_are_one_line_and_exit_2(tmp_path):
    main, sha = repo_with_script(tmp_path)
    cases = [
        (("collect", "nosuchcommit", "experiments/g"), "COMMIT 'nosuchcommit' is not a commit"),
        (("collect", "HEAD", "experiments/g"), f"exp-{sha}/experiments/g: no such directory"),
        (("start", "HEAD", "experiments/missing.toml", "experiments/g"),
         f"GRID 'experiments/missing.toml': no such file at commit {sha}"),
        (("bogus", "HEAD", "x"), "pinned.sh start COMMIT GRID.toml OUT"),
        (("run", "HEAD", "experiments/missing.toml", "experiments/g"),
         f"GRID 'experiments/missing.toml': no such file at commit {sha}"),
        (("queue", "HEAD", "experiments/g.toml"), "queue takes COMMIT GRID.toml OUT triples"),
        (("queue", "HEAD", "experiments/g.toml", "experiments/g",
          "nosuchcommit", "experiments/g.toml", "experiments/h"),
         "COMMIT 'nosuchcommit' is not a commit"),
        (("queue", "HEAD", "experiments/g.toml", "experiments/g",
          "HEAD", "experiments/missing.toml", "experiments/h"),
         f"GRID 'experiments/missing.toml': no such file at commit {sha}"),
    ]
    for args, message in cases:
        r = pinned(main, *args)
        assert r.returncode == 2, (args, r.stdout, r.stderr)
        assert message in r.stderr, (args, r.stderr)
    assert not (tmp_path / f"exp-{sha}").exists()  # a refused start made no worktree
    assert not (tmp_path / "grid-queue.log").exists()  # a refused queue started nothing


def test_queue_waits_for_the_running_grid_then_runs_each_in_turn(tmp_path):
    main, sha = repo_with_script(tmp_path)
    (main / "experiments" / "h.toml").write_text('name = "h"\n')
    git(main, "add", ".")
    git(main, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "h")
    head = git(main, "rev-parse", "--short=7", "HEAD")
    marker = f"pinned-test-grid-{uuid.uuid4().hex}"  # stands for a running grid's command line
    grid = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", marker])
    log = tmp_path / "grid-queue.log"
    env = {"PINNED_WAIT_PATTERN": marker, "PINNED_POLL_S": "0.2"}
    try:
        r = pinned(main, "queue", sha, "experiments/g.toml", "experiments/g",
                   "HEAD", "experiments/h.toml", "experiments/h", env=env)
        assert r.returncode == 0, r.stderr
        assert "queued 2 grid(s)" in r.stdout
        again = pinned(main, "queue", "HEAD", "experiments/h.toml", "experiments/h", env=env)
        assert again.returncode == 2 and "a queue is already running" in again.stderr
        time.sleep(1.5)
        assert not (tmp_path / f"exp-{sha}").exists()  # still waiting
        grid.kill()
        grid.wait()
        # each grid's turn: its worktree is laid out, and building its venv fails here
        assert wait_for(lambda: log.exists() and log.read_text().count("ended with status") == 2
                        ), log.read_text() if log.exists() else "no log"
        assert (tmp_path / f"exp-{sha}" / "experiments" / "g.toml").exists()
        assert (tmp_path / f"exp-{head}" / "experiments" / "h.toml").exists()
        text = log.read_text()
        assert text.index("experiments/g.toml ended") < text.index("experiments/h.toml ended")
        assert wait_for(lambda: not list((main / "experiments").glob(".pinned-queue-*")))
    finally:
        grid.kill()
        grid.wait()
        kill_queue(marker)


def test_the_default_wait_pattern_finds_grids_but_not_the_queue():
    """What the queue waits on (pgrep -f, an extended regex) matches a grid however it was
    started and not the queue's own command line."""
    line = next(x for x in SCRIPT.read_text().splitlines() if x.startswith("wait_pattern="))
    pattern = re.search(r":-(.*)}$", line).group(1)
    grids = [".venv/bin/python -m skyloop experiment run experiments/g.toml --out experiments/g",
             "/w/.venv/bin/python /w/.venv/bin/skyloop experiment run g.toml --out runs/g"]
    others = ["bash /w/main/experiments/pinned.sh run abc experiments/g.toml experiments/g 2",
              "bash -c script=$1 queue /w/main/experiments/.pinned-queue-x.sh abc g.toml g",
              "skyloop experiment report experiments/g"]
    assert all(re.search(pattern, g) for g in grids)
    assert not any(re.search(pattern, o) for o in others)


def kill_queue(marker: str) -> None:
    """Stop a queue this test started and left waiting (it has the marker in its
    environment, not in its command line)."""
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and marker.encode() in (proc / "environ").read_bytes():
                os.kill(int(proc.name), 9)
        except OSError:
            pass
