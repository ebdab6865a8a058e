"""The actors skyloop ships, by name: ``--policy shipped:NAME`` (``skyloop eval``, ``up``,
``policy``, ``demo``; the learner's ``--init-actor``). Each lives in its own folder with
its ``actor.pt`` and a README saying how it was trained and how it flies.
``DEFAULT_SHIPPED`` is what ``--policy shipped``, or no ``--policy`` at all, flies.

Light on purpose (no torch): command lines check a name before anything starts.
"""

from __future__ import annotations

from pathlib import Path

SHIPPED_DIR = Path(__file__).resolve().parent
SHIPPED = {"valley": "td3_abr_valley"}  # name -> folder
DEFAULT_SHIPPED = "valley"


def shipped_actor(name: str, flag: str = "--policy") -> Path:
    """The actor file of shipped policy ``name``; ValueError naming ``flag`` otherwise."""
    if name not in SHIPPED:
        raise ValueError(f"{flag} shipped:{name}: no such shipped policy (shipped: "
                         f"{', '.join(f'shipped:{n}' for n in SHIPPED)})")
    return SHIPPED_DIR / SHIPPED[name] / "actor.pt"


SHIPPED_POLICY = shipped_actor(DEFAULT_SHIPPED)


def policy_path(policy: str | Path | None, flag: str = "--policy") -> Path:
    """``None`` or ``"shipped"``: the default shipped actor; ``"shipped:NAME"``: that
    shipped actor (ValueError for an unknown name); anything else: the path (an actor
    file or a run's directory)."""
    if policy is None or str(policy) == "shipped":
        return SHIPPED_POLICY
    kind, sep, name = str(policy).partition(":")
    return shipped_actor(name, flag) if sep and kind == "shipped" else Path(policy)
