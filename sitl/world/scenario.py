"""Scenarios: typed dataclasses loaded from TOML data files in ``sitl/world/scenarios/``.

A scenario file describes a world by parameters, never by code: the navigable area,
the start/goal sampling rules, the procedural terrain (hills, ridges), static
obstacles generated from parameters (city buildings, forest trees) and moving
aircraft flying closed waypoint loops. Procedural geometry is fixed by the file's own
``seed`` field, so a scenario name always means the same world.

A file may start with ``base = "<other scenario>"``: the base file's tables are read
first and the file's own keys override them (tables are merged key by key; arrays of
tables such as ``[[aircraft]]`` replace the base's). ``dynamic.toml`` is the valley
plus three aircraft this way.

Every problem with a file raises :class:`ScenarioError` whose message names the file,
the field (dotted path, e.g. ``terrain.hills.count``) and what is wrong.
"""

from __future__ import annotations

import tomllib
import typing
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"


class ScenarioError(ValueError):
    """A scenario file is malformed or a scenario name is unknown."""


def _rng(lo: float, hi: float) -> dict[str, Any]:
    return {"range": (lo, hi)}


def _pair(lo: float, hi: float) -> dict[str, Any]:
    """Metadata of a ``[min, max]`` pair: both within [lo, hi] and min <= max."""
    return {"range": (lo, hi), "ascending": True}


@dataclass(frozen=True)
class AreaConfig:
    """The navigable area, centred on the origin; terrain extends ``margin`` beyond it."""

    size_x: float = field(default=35.0, metadata=_rng(5.0, 1000.0))  # m (east)
    size_y: float = field(default=35.0, metadata=_rng(5.0, 1000.0))  # m (north)
    margin: float = field(default=10.0, metadata=_rng(0.0, 200.0))  # m of terrain outside
    flight_level: float = field(default=3.5, metadata=_rng(0.5, 100.0))  # m, p_approAlt


@dataclass(frozen=True)
class StartGoalConfig:
    """Rules for drawing a random start and goal each episode (both at the flight level)."""

    min_distance: float = field(default=12.0, metadata=_rng(0.0, 1000.0))  # m
    max_distance: float = field(default=30.0, metadata=_rng(0.1, 1000.0))  # m
    clearance: float = field(default=1.5, metadata=_rng(0.0, 20.0))  # m free around them
    max_terrain_height: float = field(default=2.0, metadata=_rng(-100.0, 100.0))  # m below


@dataclass(frozen=True)
class HillsConfig:
    """Gaussian hills placed uniformly over the terrain (navigable area + margin)."""

    count: int = field(default=0, metadata=_rng(0, 500))
    height: tuple[float, float] = field(default=(5.0, 9.0), metadata=_pair(0.0, 200.0))
    radius: tuple[float, float] = field(default=(2.5, 4.5), metadata=_pair(0.1, 200.0))


@dataclass(frozen=True)
class RidgesConfig:
    """Ridges: Gaussian cross-section along a straight segment, tapering at both ends."""

    count: int = field(default=0, metadata=_rng(0, 200))
    height: tuple[float, float] = field(default=(5.0, 8.0), metadata=_pair(0.0, 200.0))
    length: tuple[float, float] = field(default=(8.0, 16.0), metadata=_pair(0.1, 500.0))
    width: tuple[float, float] = field(default=(1.5, 2.5), metadata=_pair(0.1, 100.0))


@dataclass(frozen=True)
class TerrainConfig:
    """Heightfield: grid spacing, gentle undulation, hills and ridges."""

    resolution: float = field(default=0.25, metadata=_rng(0.05, 10.0))  # m grid spacing
    roughness: float = field(default=0.3, metadata=_rng(0.0, 20.0))  # m amplitude
    roughness_wavelength: float = field(default=12.0, metadata=_rng(0.5, 1000.0))  # m
    hills: HillsConfig = HillsConfig()
    ridges: RidgesConfig = RidgesConfig()


@dataclass(frozen=True)
class BuildingsConfig:
    """City blocks on a regular grid; streets between blocks keep the city passable."""

    block: float = field(default=9.0, metadata=_rng(1.0, 200.0))  # m block pitch
    street: float = field(default=4.0, metadata=_rng(0.5, 100.0))  # m min street width
    fill: float = field(default=0.0, metadata=_rng(0.0, 1.0))  # P(block has a building)
    min_size: float = field(default=3.0, metadata=_rng(0.2, 200.0))  # m footprint side
    height: tuple[float, float] = field(default=(5.0, 15.0), metadata=_pair(0.1, 500.0))


@dataclass(frozen=True)
class TreesConfig:
    """Conifer-like trees: a prism trunk and a pyramid-frustum crown (convex solids)."""

    count: int = field(default=0, metadata=_rng(0, 5000))
    height: tuple[float, float] = field(default=(6.0, 10.0), metadata=_pair(0.5, 100.0))
    crown_radius: tuple[float, float] = field(default=(1.2, 2.2), metadata=_pair(0.1, 50.0))
    crown_base: tuple[float, float] = field(default=(1.0, 2.0), metadata=_pair(0.0, 50.0))
    trunk_radius: float = field(default=0.15, metadata=_rng(0.01, 5.0))
    sides: int = field(default=8, metadata=_rng(3, 64))
    min_gap: float = field(default=1.5, metadata=_rng(0.0, 100.0))  # m between crowns


@dataclass(frozen=True)
class AircraftConfig:
    """A moving aircraft: a yawed box flying a closed waypoint loop at constant speed."""

    waypoints: tuple[tuple[float, float, float], ...] = field(metadata={"min_len": 2})
    speed: float = field(default=1.5, metadata=_rng(0.0, 100.0))  # m/s
    size: tuple[float, float, float] = field(
        default=(1.2, 1.5, 0.4), metadata=_rng(0.01, 100.0)
    )  # m: length, wingspan, height
    phase: float = field(default=0.0, metadata=_rng(0.0, 1.0))  # start, fraction of the loop
    name: str = ""


@dataclass(frozen=True)
class Scenario:
    """One world: its geometry is fixed by ``seed``; start/goal are drawn per episode."""

    name: str
    seed: int = field(metadata=_rng(0, 2**63 - 1))
    description: str = ""
    area: AreaConfig = AreaConfig()
    start_goal: StartGoalConfig = StartGoalConfig()
    terrain: TerrainConfig = TerrainConfig()
    buildings: BuildingsConfig = BuildingsConfig()
    trees: TreesConfig = TreesConfig()
    aircraft: tuple[AircraftConfig, ...] = ()
    source: str = field(default="", metadata={"internal": True})  # file it was read from


# --- loading -------------------------------------------------------------------------


def scenario_names() -> list[str]:
    """Names of the scenario files shipped in ``sitl/world/scenarios/`` (sorted)."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a scenario by name (``sitl/world/scenarios/<name>.toml``) or by file path;
    ``NAME#SEED`` is world ``SEED`` of the family ``NAME`` (:func:`world_variant`)."""
    text = str(name_or_path)
    if not isinstance(name_or_path, Path) and "#" in text:
        family, _, seed_text = text.rpartition("#")
        try:
            seed = int(seed_text)
        except ValueError:
            raise ScenarioError(f"{text}: the world seed after '#' must be an integer, "
                                f"got {seed_text!r}") from None
        if not 0 <= seed < 2**63:
            raise ScenarioError(f"{text}: the world seed must be in [0, 2**63), got {seed}")
        return world_variant(load_scenario(family), seed)
    path = _resolve(name_or_path)
    data = _read_with_base(path, seen=())
    data.pop("base", None)
    scenario = _build(Scenario, data, "", path.name)
    _check_scenario(scenario, path.name)
    return _replace_source(scenario, str(path))


def world_variant(scenario: Scenario, seed: int) -> Scenario:
    """World ``seed`` of the family ``scenario`` is a template for: the same parameters
    with their own seed (so new terrain, hills, ridges, trees and buildings), and the
    aircraft loops turned about the area's centre by an angle, mirrored or not, and
    started at phases, all drawn from ``seed``. Named ``<family>#<seed>``."""
    from dataclasses import replace

    rng = np.random.default_rng([seed, 0x51A7])  # not the stream World draws from
    angle, mirror = float(rng.uniform(0.0, 2 * np.pi)), bool(rng.integers(2))
    c, s_ = np.cos(angle), np.sin(angle)
    aircraft = []
    for a in scenario.aircraft:
        wps = []
        for x, y, z in a.waypoints:
            x = -x if mirror else x
            wps.append((float(c * x - s_ * y), float(s_ * x + c * y), float(z)))
        aircraft.append(replace(a, waypoints=tuple(wps), phase=float(rng.uniform(0.0, 1.0))))
    return replace(scenario, name=f"{scenario.name}#{seed}", seed=int(seed),
                   aircraft=tuple(aircraft))


def _resolve(name_or_path: str | Path) -> Path:
    text = str(name_or_path)
    if isinstance(name_or_path, Path) or text.endswith(".toml") or "/" in text:
        path = Path(name_or_path)
        if not path.is_file():
            raise ScenarioError(f"{path}: scenario file not found")
        return path
    path = SCENARIO_DIR / f"{text}.toml"
    if not path.is_file():
        known = ", ".join(scenario_names())
        raise ScenarioError(f"unknown scenario '{text}' (known: {known})")
    return path


def _read_with_base(path: Path, seen: tuple[Path, ...]) -> dict[str, Any]:
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(f"{path.name}: invalid TOML syntax: {e}") from e
    except OSError as e:
        raise ScenarioError(f"{path.name}: cannot read: {e}") from e
    base = data.get("base")
    if base is None:
        return data
    if not isinstance(base, str):
        raise ScenarioError(f"{path.name}: field 'base': expected a scenario name (string)")
    base_path = SCENARIO_DIR / f"{base}.toml"
    if not base_path.is_file():
        known = ", ".join(scenario_names())
        raise ScenarioError(
            f"{path.name}: field 'base': unknown scenario '{base}' (known: {known})")
    if base_path.resolve() in seen:
        raise ScenarioError(f"{path.name}: field 'base': circular base '{base}'")
    merged = _read_with_base(base_path, seen + (path.resolve(),))
    merged.pop("base", None)
    return _merge(merged, data)


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _replace_source(s: Scenario, source: str) -> Scenario:
    from dataclasses import replace

    return replace(s, source=source)


def _fail(file: str, path: str, what: str) -> typing.NoReturn:
    raise ScenarioError(f"{file}: field '{path}': {what}")


def _describe(value: Any) -> str:
    return f"{type(value).__name__} {value!r}"


def _build(cls: type, data: Any, prefix: str, file: str) -> Any:
    """Build dataclass ``cls`` from a TOML table, checking names, types and ranges."""
    if not isinstance(data, dict):
        _fail(file, prefix.rstrip(".") or "<root>", f"expected a table, got {_describe(data)}")
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in fields(cls) if not f.metadata.get("internal")}
    for key in data:
        if key not in known:
            names = ", ".join(sorted(known))
            _fail(file, f"{prefix}{key}", f"unknown field (known: {names})")
    kwargs: dict[str, Any] = {}
    for name, f in known.items():
        path = f"{prefix}{name}"
        if name not in data:
            if f.default is MISSING and f.default_factory is MISSING:
                _fail(file, path, "missing (required)")
            continue
        value = _convert(hints[name], data[name], path, file)
        _check_meta(f.metadata, value, path, file)
        kwargs[name] = value
    return cls(**kwargs)


def _convert(tp: Any, value: Any, path: str, file: str) -> Any:
    origin = typing.get_origin(tp)
    if isinstance(tp, type) and hasattr(tp, "__dataclass_fields__"):
        return _build(tp, value, path + ".", file)
    if tp is bool:
        if not isinstance(value, bool):
            _fail(file, path, f"expected true or false, got {_describe(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            _fail(file, path, f"expected an integer, got {_describe(value)}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            _fail(file, path, f"expected a number, got {_describe(value)}")
        if value != value or value in (float("inf"), float("-inf")):
            _fail(file, path, f"expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            _fail(file, path, f"expected a string, got {_describe(value)}")
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list):
            _fail(file, path, f"expected an array, got {_describe(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{path}[{i}]", file) for i, v in enumerate(value))
        if len(value) != len(args):
            _fail(file, path, f"expected an array of {len(args)} values, got {len(value)}")
        pairs = enumerate(zip(args, value, strict=True))
        return tuple(_convert(a, v, f"{path}[{i}]", file) for i, (a, v) in pairs)
    raise TypeError(f"unsupported schema type {tp}")  # pragma: no cover


def _numbers(value: Any) -> list[float]:
    if isinstance(value, tuple):
        out: list[float] = []
        for v in value:
            out.extend(_numbers(v))
        return out
    if isinstance(value, int | float) and not isinstance(value, bool):
        return [float(value)]
    return []


def _check_meta(meta: Any, value: Any, path: str, file: str) -> None:
    if "range" in meta:
        lo, hi = meta["range"]
        for v in _numbers(value):
            if not lo <= v <= hi:
                _fail(file, path, f"value {v:g} out of range [{lo:g}, {hi:g}]")
    if meta.get("ascending") and value[0] > value[1]:
        _fail(file, path, f"expected [min, max] with min <= max, got {list(value)}")
    if "min_len" in meta and len(value) < meta["min_len"]:
        _fail(file, path, f"expected at least {meta['min_len']} entries, got {len(value)}")


def _check_scenario(s: Scenario, file: str) -> None:
    """Cross-field checks that a single field's range cannot express."""
    sg, area = s.start_goal, s.area
    if sg.min_distance > sg.max_distance:
        _fail(file, "start_goal.min_distance",
              f"{sg.min_distance:g} > max_distance {sg.max_distance:g}")
    diag = (area.size_x**2 + area.size_y**2) ** 0.5
    if sg.min_distance > diag:
        _fail(file, "start_goal.min_distance",
              f"{sg.min_distance:g} m exceeds the area's diagonal {diag:.1f} m")
    if sg.max_terrain_height >= area.flight_level:
        _fail(file, "start_goal.max_terrain_height",
              f"{sg.max_terrain_height:g} must be below the flight level {area.flight_level:g}")
    b = s.buildings
    if b.fill > 0 and b.min_size + b.street > b.block:
        _fail(file, "buildings.block",
              f"{b.block:g} m is smaller than min_size + street = {b.min_size + b.street:g} m")
    for i, ac in enumerate(s.aircraft):
        if ac.speed <= 0:
            _fail(file, f"aircraft[{i}].speed", "must be > 0")
