"""experiments/pinned.sh: a grid's finished trials come home without checkpoints, and bad
arguments are one line with exit 2. The script runs in a small git repository of its own
(a copy of the script, one commit) beside a worktree directory laid out as a running grid
leaves it; `start` is exercised only on its refusals (it builds a venv and runs a grid)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "experiments" / "pinned.sh"


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


def pinned(main: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "experiments/pinned.sh", *args], cwd=main,
                          capture_output=True, text=True, timeout=60)


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


def test_bad_arguments_are_one_line_and_exit_2(tmp_path):
    main, sha = repo_with_script(tmp_path)
    cases = [
        (("collect", "nosuchcommit", "experiments/g"), "COMMIT 'nosuchcommit' is not a commit"),
        (("collect", "HEAD", "experiments/g"), f"exp-{sha}/experiments/g: no such directory"),
        (("start", "HEAD", "experiments/missing.toml", "experiments/g"),
         f"GRID 'experiments/missing.toml': no such file at commit {sha}"),
        (("bogus", "HEAD", "x"), "pinned.sh start COMMIT GRID.toml OUT"),
    ]
    for args, message in cases:
        r = pinned(main, *args)
        assert r.returncode == 2, (args, r.stdout, r.stderr)
        assert message in r.stderr, (args, r.stderr)
    assert not (tmp_path / f"exp-{sha}").exists()  # a refused start made no worktree
