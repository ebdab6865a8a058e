"""Average the weights of a run's kept actors (issue 14: a probe, not the pick's rule).

A mixture run's kept actors swing by 10-20 points of validation success from one
snapshot to the next (``RUN/validation.png``). Averaging the weights of consecutive
policies of one run (weight averaging, Nikishin et al. 2018, "Improving Stability in
Deep Reinforcement Learning with Weight Averaging"; SWA, Izmailov et al. 2018) is the
textbook cure: theta = (1/K) sum_k theta_k over the actors kept at training episodes
``--first`` .. ``--last``. The result is an actor file like any other (the last
averaged actor's task, observation and config), flown with ``skyloop eval``.

    python experiments/general/average_actors.py RUN --first 2100 --last 3000 --out FILE
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from pick_by_validation import actors


def average(paths: list[Path]) -> dict:
    """The actor file of the mean of ``paths``' actor weights (eq. above); every other
    field from the last file. Files of different shapes or tasks raise ValueError."""
    states = [torch.load(p, map_location="cpu", weights_only=True) for p in paths]
    last = states[-1]
    for path, s in zip(paths, states, strict=True):
        for key in ("format", "config", "task", "observation"):
            if s.get(key) != last.get(key):
                raise ValueError(f"{path}: its {key} differs from {paths[-1]}'s")
    mean = {name: torch.stack([s["actor"][name].float() for s in states]).mean(0)
            for name in last["actor"]}
    return {**last, "actor": mean}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path)
    p.add_argument("--first", type=int, required=True, help="first training episode kept")
    p.add_argument("--last", type=int, required=True, help="last training episode kept")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    if not (args.run / "episodes.csv").is_file():
        p.error(f"{args.run}: not a training run (no episodes.csv)")
    chosen = [path for episode, path in actors(args.run)
              if args.first <= episode <= args.last]
    if len(chosen) < 2:
        p.error(f"--first {args.first} --last {args.last}: {len(chosen)} kept actor(s) "
                f"of {args.run} in that range; need 2 or more")
    try:
        state = average(chosen)
    except ValueError as exc:
        p.error(str(exc))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(state, args.out)
    print(f"wrote {args.out}: the mean of {len(chosen)} actors "
          f"({chosen[0].name} .. {chosen[-1].name})")


if __name__ == "__main__":
    main()
