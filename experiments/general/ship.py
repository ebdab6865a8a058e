"""From a finished mixture grid to a shipped policy (issue 14), by validation worlds only.

1. Every finished trial of the grid (``--jobs`` at once): each kept actor on the
   validation worlds of every family, screened (``pick_by_validation.screened``: every
   actor ``--screen`` episodes, the ``--keep`` best the full ``--episodes``, the
   ``--final-keep`` best of those ``--final``; resumable, ``TRIAL/selection.jsonl``), and
   the trial's pick (largest worst margin over the goals, on the last round).
2. Across trials: the pick with the largest worst margin (earliest trial on ties).
3. That one actor, once, on the **held-out** worlds (``--heldout-episodes`` per family
   over ``--heldout-worlds`` worlds, episode seeds from 1,000,000,000), beside the
   valley-only policy's table (``experiments/general/baseline-valley-policy-*.json``):
   the issue's goals and "no family worse than the valley policy" checked (worse: below
   it at one-sided p < 0.05, Fisher's exact test; decided before any held-out flight of a
   mixture pick, and the table shows the point differences too).
4. ``--out policy/shipped/NAME``: the actor, its training CSV and curve, the held-out
   JSONs, the validation table and a README with the commands and the table. Making it
   the default (``policy/shipped/__init__.py``) is a decision left to a person, with the
   table in front of them.

    python experiments/general/ship.py experiments/general_mix [--out policy/shipped/NAME]
"""

from __future__ import annotations

import argparse
import json
import shutil
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path

from pick_by_validation import GOALS, add_round_flags, choose, last_round, margin, positive_int

from policy.shipped import SHIPPED, SHIPPED_DIR

HERE = Path(__file__).resolve().parent


def validate_trial(trial: Path, episodes: int, worlds: int, screen: int, keep: int,
                   final: int, final_keep: int) -> dict:
    """One trial validated and its pick (``choose``), its figure ``TRIAL/validation.png``."""
    return choose(trial, episodes, worlds, screen, keep, trial / "validation.png", final,
                  final_keep)


def heldout(actor: str, out: Path, episodes: int, worlds: int) -> dict[str, dict]:
    """The actor on the held-out worlds of each family (cached as JSON in ``out``)."""
    from policy.training.evaluate import evaluate

    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for family in GOALS:
        path = out / f"eval-heldout-{family}.json"
        cached = json.loads(path.read_text()) if path.is_file() else {}
        if (cached.get("policy"), cached.get("episodes"), cached.get("worlds")) \
                == (f"actor {actor}", episodes, worlds):  # the same actor and settings
            results[family] = cached
            continue
        results[family] = evaluate(actor, f"family:{family}", episodes, worlds=worlds,
                                   json_path=path, progress=False)
        print(f"held out {family}: {results[family]['success_rate']:.1%}", flush=True)
    return results


def worse_p(s: dict, base: dict) -> float:
    """One-sided p that this policy's success rate is below the valley policy's (Fisher's
    exact test on the two 2x2 counts, ``scipy.stats.fisher_exact``)."""
    from scipy.stats import fisher_exact

    def counts(r: dict) -> list[int]:
        wins = round(r["success_rate"] * r["episodes"])
        return [wins, r["episodes"] - wins]

    return float(fisher_exact([counts(s), counts(base)], alternative="less").pvalue)


def table(results: dict[str, dict]) -> tuple[str, bool]:
    """The held-out table beside the valley policy's, and whether every goal holds: the
    issue's rate, and no family worse than the valley policy, "worse" meaning below it
    at one-sided p < 0.05 (``worse_p``; 200 episodes each cannot tell a point or two).
    The table also says where the point estimate alone is below."""
    lines = ["| family | this policy (95% CI) | collision | timeout | valley-only policy | "
             "difference (p below) | goal |", "|---|---|---|---|---|---|---|"]
    met = True
    for family, goal in GOALS.items():
        s = results[family]
        base = json.loads((HERE / f"baseline-valley-policy-{family}.json").read_text())
        lo, hi = s["success_ci95"]
        p = worse_p(s, base)
        ok = s["success_rate"] >= goal and p >= 0.05
        met &= ok
        lines.append(f"| {family} | {s['success_rate']:.1%} ({lo:.1%}-{hi:.1%}) | "
                     f"{s['collision_rate']:.1%} | {s['timeout_rate']:.1%} | "
                     f"{base['success_rate']:.1%} | "
                     f"{s['success_rate'] - base['success_rate']:+.1%} (p {p:.2f}) | "
                     f">= {goal:.0%}, not below the valley policy: "
                     f"{'met' if ok else '**not met**'} |")
    return "\n".join(lines), met


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("grid", type=Path, help="the mixture grid's output directory")
    p.add_argument("--episodes", type=positive_int, default=60, help="validation, per family")
    p.add_argument("--worlds", type=positive_int, default=20,
                   help="validation worlds per family")
    add_round_flags(p)
    p.add_argument("--jobs", type=positive_int, default=1,
                   help="trials validated at once (a process each, one core each)")
    p.add_argument("--heldout-episodes", type=positive_int, default=200)
    p.add_argument("--heldout-worlds", type=positive_int, default=50)
    p.add_argument("--out", type=Path, default=None, help="policy/shipped/NAME to write")
    args = p.parse_args()
    if not args.grid.is_dir():
        p.error(f"{args.grid}: no such directory")
    if args.out is not None and args.out.resolve().name in SHIPPED.values() \
            and args.out.resolve().parent == SHIPPED_DIR:
        p.error(f"--out {args.out}: already a shipped policy (policy/shipped/__init__.py); "
                f"give a new folder")

    trials = sorted(d for d in args.grid.iterdir() if (d / "result.json").is_file())
    if not trials:
        raise SystemExit(f"{args.grid}: no finished trial (TRIAL/result.json)")
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        picks = list(pool.map(partial(validate_trial, episodes=args.episodes,
                                      worlds=args.worlds, screen=args.screen,
                                      keep=args.keep, final=args.final,
                                      final_keep=args.final_keep), trials))
    best = max(picks, key=lambda c: c["margin"])  # the first trial on ties
    (args.grid / "selection.json").write_text(json.dumps(
        {"pick": best, "trials": picks}, indent=2) + "\n")
    print(f"grid pick: {best['actor']} (worst validation margin {best['margin']:+.1%})")
    if args.out is None:
        return

    results = heldout(best["actor"], args.out, args.heldout_episodes, args.heldout_worlds)
    text, met = table(results)
    run = Path(best["run"])
    shutil.copyfile(best["actor"], args.out / "actor.pt")
    for name in ("episodes.csv", "curve.png", "config.json", "validation.png",
                 "selection.jsonl"):
        if (run / name).is_file():
            shutil.copyfile(run / name, args.out / name)
    validation = "\n".join(
        f"| {Path(c['run']).name} | {c['episode']} | " + " | ".join(
            f"{c['validation_success'][f]:.0%}" for f in GOALS) + f" | {c['margin']:+.1%} |"
        for c in picks)
    screening = (f", every actor first {args.screen} episodes per family and the "
                 f"{args.keep} best of each trial the full {args.episodes}"
                 if 0 < args.screen < args.episodes else "")
    final = last_round(args.episodes, args.final)
    if final > args.episodes:
        screening += (f", then the {args.final_keep} best of those {final} episodes per "
                      f"family, on which the pick is made")
    title = f"{args.out.name}: a mixture policy picked by validation worlds"
    (args.out / "README.md").write_text(f"""# {title}

`actor.pt` is the actor kept at training episode {best['episode']} of `{run.name}` in the
mixture grid `{args.grid}` (`config.json`: its training settings; `episodes.csv`,
`curve.png`: its training run), picked by validation worlds only:

    python experiments/general/ship.py {args.grid} --episodes {args.episodes} \\
        --worlds {args.worlds} --screen {args.screen} --keep {args.keep} \\
        --final {args.final} --final-keep {args.final_keep} --out {args.out}

## The pick: validation worlds ({args.worlds} per family, {final} episodes each)

Each trial's kept actors were flown on validation worlds (seeds 2,147,483,648 + i){screening}; a
trial's pick is the actor with the largest worst margin over the goals
(min over families of success - goal; `validation.png`), and the grid's pick the best of
those.

| trial | episode | {' | '.join(GOALS)} | worst margin |
|---|---|{'---|' * len(GOALS)}---|
{validation}

## Held out: {args.heldout_episodes} episodes per family

Over {args.heldout_worlds} worlds per family never trained or validated on: world seeds
3,221,225,472 + i, episode seeds from 1,000,000,000 (`eval-heldout-*.json`):

    skyloop eval --policy {args.out / 'actor.pt'} --scenario family:FAMILY \\
        --worlds {args.heldout_worlds} --episodes {args.heldout_episodes}

{text}

{'Every goal of issue 14 holds.' if met else '**Not every goal of issue 14 holds.**'}
""")
    print(text)
    print(f"wrote {args.out}; every goal {'met' if met else 'NOT met'}; worst margin "
          f"{margin({f: results[f]['success_rate'] for f in GOALS}):+.1%} held out")


if __name__ == "__main__":
    main()
