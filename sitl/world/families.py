"""Worlds drawn per episode: families of the shipped scenarios, and mixtures of families.

What ``--scenario`` (and ``EpisodeConfig.scenario``) takes:

- ``NAME`` (``valley``, a file path, ``city#123``): one fixed world, as always;
- ``family:NAME``: a fresh world of family ``NAME`` (the shipped scenario as template:
  :func:`sitl.world.scenario.world_variant`) every ``world_every`` episodes;
- ``mix:A,B,C`` or ``mix:A=2,B=1``: the family drawn per new world with these weights
  (equal when none are given).

Worlds are named ``<family>#<seed>``, a name :func:`sitl.world.scenario.load_scenario` reads,
so a log's episode (its START names the world) can be rebuilt anywhere. World seeds
come from disjoint ranges, so that evaluation worlds are never trained on:

- training: drawn uniformly from ``[0, 2**31)`` (:data:`TRAIN_SEEDS`) with the episode's
  generator, so the same episode seed gives the same world and the same episode;
- validation (for choosing among trained policies): ``VALIDATION_SEED0 + i``;
- held-out evaluation: ``EVAL_SEED0 + i`` (``skyloop eval --scenario family:NAME
  --worlds N`` flies worlds ``i = 0 .. N-1``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sitl.world.scenario import ScenarioError, scenario_names

TRAIN_SEEDS = (0, 2**31)
VALIDATION_SEED0 = 2**31
EVAL_SEED0 = 2**31 + 2**30


@dataclass(frozen=True)
class WorldSource:
    """Where an episode's world comes from (see the module docstring)."""

    spec: str
    families: tuple[str, ...] = ()  # empty: the fixed world ``spec``
    weights: tuple[float, ...] = ()

    @property
    def fixed(self) -> bool:
        return not self.families

    @classmethod
    def parse(cls, spec: str) -> WorldSource:
        """``NAME`` | ``family:NAME`` | ``mix:A[=w],B[=w],...``; ScenarioError naming the
        spec and the part that is wrong."""
        kind, sep, rest = spec.partition(":")
        if not sep or kind not in ("family", "mix"):
            return cls(spec)
        parts = [p.strip() for p in rest.split(",") if p.strip()]
        if not parts or (kind == "family" and len(parts) != 1):
            raise ScenarioError(f"scenario {spec!r}: {kind}: needs "
                                + ("one family name" if kind == "family" else "family names"))
        families, weights = [], []
        for part in parts:
            name, eq, w = part.partition("=")
            if name not in scenario_names():
                raise ScenarioError(f"scenario {spec!r}: unknown family {name!r} (known: "
                                    f"{', '.join(scenario_names())})")
            try:
                weight = float(w) if eq else 1.0
            except ValueError:
                raise ScenarioError(f"scenario {spec!r}: weight of {name!r} must be a number, "
                                    f"got {w!r}") from None
            if not weight > 0 or not np.isfinite(weight):
                raise ScenarioError(f"scenario {spec!r}: weight of {name!r} must be > 0")
            families.append(name)
            weights.append(weight)
        return cls(spec, tuple(families), tuple(weights))

    def template(self) -> str:
        """The world to start from: the fixed world, or the first family's template."""
        return self.spec if self.fixed else self.families[0]

    def draw(self, rng: np.random.Generator) -> str:
        """A training world's name: the family by weight, the seed from TRAIN_SEEDS."""
        p = np.asarray(self.weights) / sum(self.weights)
        family = self.families[int(rng.choice(len(self.families), p=p))] \
            if len(self.families) > 1 else self.families[0]
        return f"{family}#{int(rng.integers(*TRAIN_SEEDS))}"


def check_scenario(spec: str) -> WorldSource:
    """The world source of ``spec``, its scenario files loaded once to check them
    (ScenarioError naming the file and field, or the spec)."""
    from sitl.world.scenario import load_scenario

    source = WorldSource.parse(spec)
    for name in source.families or (spec,):
        load_scenario(name)
    return source


def eval_worlds(family: str, n: int, *, validation: bool = False) -> list[str]:
    """The ``n`` held-out (or validation) worlds of ``family``, never drawn in training."""
    seed0 = VALIDATION_SEED0 if validation else EVAL_SEED0
    return [f"{family}#{seed0 + i}" for i in range(n)]
