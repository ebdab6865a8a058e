"""Pick a mixture run's policy by validation worlds only (issue 14).

A mixture run's last actor is not its best (experiments/general/README.md: seed 0 lost
the open worlds after episode ~600), so every actor the run kept over training
(``RUN/snapshots/actor-ep<N>.pt``, and ``RUN/actor.pt``, the last) flies
``--episodes`` episodes on ``--worlds`` **validation** worlds of each family
(``sitl.world.families.eval_worlds(..., validation=True)``: seeds from 2,147,483,648, disjoint
from training and from the held-out worlds the final table uses).

The pick: the actor with the largest worst margin over the issue's goals,
``min_f(success_f - goal_f)`` (valley, forest, dynamic 0.90; city 0.85); ties go to the
earlier actor. With ``--screen N`` (default 20) every actor first flies N episodes per
family and only the ``--keep`` best (default 4) fly the full ``--episodes``: the one
round of successive halving cuts a 31-actor run's validation from 7,440 episodes to
3,440. Then the ``--final-keep`` best of those (default 2) fly ``--final`` episodes
(default 200, as many as the held-out table) and the pick is made on those: 60 episodes
could not tell 92% from 81% (experiments/general/README.md: the first grid's pick), and
the best of many noisy actors is the lucky one, so the last word goes to a count whose
95% interval is about +-4 points, not +-7. Results are appended to ``RUN/selection.jsonl``
as they come (a rerun skips what is there: resumable), the pick goes to
``RUN/selection.json`` and a figure of success per family over training to ``--plot``.

    python experiments/general/pick_by_validation.py RUN_DIR \
        [--episodes 60 --worlds 20] [--screen 20 --keep 4] [--final 200 --final-keep 2] \
        [--plot FIG]
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

GOALS = {"valley": 0.90, "forest": 0.90, "city": 0.85, "dynamic": 0.90}


def actors(run: Path) -> list[tuple[int, Path]]:
    """(training episode, actor file) of every kept actor, oldest first."""
    found = []
    for path in (run / "snapshots").glob("actor-ep*.pt"):
        match = re.fullmatch(r"actor-ep(\d+)\.pt", path.name)
        if match:
            found.append((int(match.group(1)), path))
    last = run / "actor.pt"
    episodes = sum(1 for _ in (run / "episodes.csv").open()) - 1
    if last.is_file() and (run / "result.json").is_file() \
            and episodes not in {e for e, _ in found}:
        found.append((episodes, last))  # a finished run's final actor
    return sorted(found)


def positive_int(text: str) -> int:
    """argparse type: an integer of at least 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def count_or_zero(text: str) -> int:
    """argparse type: 0 (a round left out) or a positive integer."""
    return 0 if text == "0" else positive_int(text)


def last_round(episodes: int, final: int) -> int:
    """Episodes per family of the round the pick is made on (``screened``)."""
    return final if final > episodes else episodes


def margin(rates: dict[str, float]) -> float:
    """The worst family's success minus its goal (>= 0: every goal met)."""
    return min(rates[f] - GOALS[f] for f in GOALS)


def validate(run: Path, episodes: int = 60, worlds: int = 20,
             only: set[int] | None = None) -> list[dict]:
    """Every kept actor of ``run`` (or those of the training episodes ``only``) on the
    validation worlds of every family; rows are appended to ``RUN/selection.jsonl`` as
    they come and a rerun skips what is there."""
    from policy.training.evaluate import evaluate

    if not (run / "episodes.csv").is_file():
        raise SystemExit(f"{run}: not a training run (no episodes.csv)")
    log = run / "selection.jsonl"
    done = [json.loads(line) for line in log.open()] if log.is_file() else []
    done = [d for d in done if (d["episodes"], d["worlds"]) == (episodes, worlds)]
    seen = {(d["episode"], d["family"]) for d in done}
    for episode, path in actors(run):
        if only is not None and episode not in only:
            continue
        for family in GOALS:
            if (episode, family) in seen:
                continue
            s = evaluate(str(path), f"family:{family}", episodes, worlds=worlds,
                         validation=True, progress=False)
            row = {"episode": episode, "family": family, "actor": str(path),
                   "success": s["success_rate"], "collision": s["collision_rate"],
                   "timeout": s["timeout_rate"], "episodes": s["episodes"],
                   "worlds": worlds}
            done.append(row)
            with log.open("a") as f:
                f.write(json.dumps(row) + "\n")
            print(f"{run.name} ep {episode:5d} {family:8s} success {row['success']:.1%} "
                  f"timeout {row['timeout']:.1%}", flush=True)
    return done


def best_of(rows: list[dict], keep: int) -> set[int]:
    """The training episodes of the ``keep`` actors of ``rows`` with the largest worst
    margin (earliest on ties)."""
    table = success_table(rows)
    return set(sorted(table, key=lambda e: (-margin(table[e]), e))[:keep])


def screened(run: Path, episodes: int, worlds: int, screen: int = 0, keep: int = 4,
             final: int = 0, final_keep: int = 2) -> tuple[list[dict], list[dict]]:
    """Successive halving: every kept actor on ``screen`` episodes per family, the
    ``keep`` best of them (worst margin; earliest on ties) on ``episodes``, and with
    ``final`` above ``episodes`` the ``final_keep`` best of those on ``final``. Returns
    (the first round's rows, the last round's rows); with ``screen`` 0 (or not below
    ``episodes``) every actor gets ``episodes`` in the first round."""
    if 0 < screen < episodes:
        seen = validate(run, screen, worlds)
        rows = validate(run, episodes, worlds, only=best_of(seen, keep))
    else:
        seen = rows = validate(run, episodes, worlds)
    if final > episodes:
        rows = validate(run, final, worlds, only=best_of(rows, final_keep))
    return seen, rows


def choose(run: Path, episodes: int = 60, worlds: int = 20, screen: int = 0,
           keep: int = 4, figure: Path | None = None, final: int = 0,
           final_keep: int = 2) -> dict:
    """Validate (``screened``), pick (``pick``, on the last round's rows) and draw
    (``plot``, over the first round's rows: every actor) one run; the pick."""
    seen, rows = screened(run, episodes, worlds, screen, keep, final, final_keep)
    choice = pick(run, rows, last_round(episodes, final), worlds)
    if figure is not None:
        plot(run, seen, choice["episode"], figure,
             screen if 0 < screen < episodes else episodes, worlds)
    return choice


def success_table(rows: list[dict]) -> dict[int, dict[str, float]]:
    """{training episode: {family: validation success}} of the actors seen on every
    family."""
    table: dict[int, dict[str, float]] = {}
    for d in rows:
        table.setdefault(d["episode"], {})[d["family"]] = d["success"]
    return {e: r for e, r in table.items() if set(r) == set(GOALS)}


def pick(run: Path, rows: list[dict], episodes: int, worlds: int) -> dict:
    """The actor of ``run`` with the largest worst margin (earliest on ties), written
    to ``RUN/selection.json``."""
    complete = success_table(rows)
    if not complete:
        raise SystemExit(f"{run}: no actor evaluated on every family yet")
    best = max(sorted(complete), key=lambda e: margin(complete[e]))  # earliest on ties
    kept = dict(actors(run))  # the file as it is now (the log's path may be elsewhere)
    if best not in kept:
        raise SystemExit(f"{run}: the actor of episode {best} is gone (snapshots/)")
    actor = str(kept[best])
    choice = {"run": str(run), "episode": best, "actor": actor,
              "validation_success": complete[best], "margin": margin(complete[best]),
              "goals": GOALS, "episodes_per_family": episodes, "worlds": worlds}
    (run / "selection.json").write_text(json.dumps(choice, indent=2))
    print(f"pick: episode {best} ({actor}), worst margin {choice['margin']:+.1%}: "
          + ", ".join(f"{f} {v:.0%}" for f, v in complete[best].items()))
    return choice


def plot(run: Path, rows: list[dict], best: int, out: Path, episodes: int,
         worlds: int) -> None:
    """Validation success per family over training, the pick marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = success_table(rows)
    fig, ax = plt.subplots(figsize=(7, 4))
    for family in GOALS:
        xs = sorted(table)
        ax.plot(xs, [table[e][family] for e in xs], marker="o", ms=3, label=family)
    ax.axvline(best, color="k", lw=0.8, ls="--", label=f"pick (episode {best})")
    ax.set(title=f"{run.name}\nvalidation worlds ({worlds} per family, {episodes} "
                 f"episodes per family and actor)", xlabel="training episode of the actor",
           ylabel="success", ylim=(0, 1))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    print(f"wrote {out}")


def add_round_flags(p: argparse.ArgumentParser) -> None:
    """--screen, --keep, --final and --final-keep (``screened``), for this script and
    ship.py."""
    p.add_argument("--screen", type=count_or_zero,
                   default=20, help=(
        "first fly every actor this many episodes per family, and only the --keep best "
        "the full --episodes (0: every actor the full --episodes)"))
    p.add_argument("--keep", type=positive_int, default=4,
                   help="actors the screen passes on")
    p.add_argument("--final", type=count_or_zero,
                   default=200, help=(
        "then fly the --final-keep best of those this many episodes per family and pick "
        "on them (0, or not above --episodes: pick on --episodes)"))
    p.add_argument("--final-keep", type=positive_int, default=2,
                   help="actors the full round passes on to the final one")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path)
    p.add_argument("--episodes", type=positive_int, default=60, help="per family and actor")
    p.add_argument("--worlds", type=positive_int, default=20,
                   help="validation worlds per family")
    add_round_flags(p)
    p.add_argument("--plot", type=Path, default=None)
    args = p.parse_args()
    choose(args.run, args.episodes, args.worlds, args.screen, args.keep, args.plot,
           args.final, args.final_keep)


if __name__ == "__main__":
    main()
