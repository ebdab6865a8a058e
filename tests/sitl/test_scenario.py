"""Scenario files: loading, inheritance and precise error messages."""

from __future__ import annotations

from pathlib import Path

import pytest

from sitl.world.scenario import SCENARIO_DIR, Scenario
from sitl.world.world import ScenarioError, load_scenario, scenario_names

GOOD = """
name = "tiny"
seed = 3
[area]
size_x = 35.0
size_y = 35.0
[terrain.hills]
count = 2
"""


def write(tmp_path: Path, text: str, name: str = "bad.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_names_and_all_load() -> None:
    assert scenario_names() == ["city", "dynamic", "forest", "valley"]
    for name in scenario_names():
        s = load_scenario(name)
        assert isinstance(s, Scenario)
        assert s.name == name
        assert 900 <= s.area.size_x * s.area.size_y <= 1600  # the paper's ~1200 m^2
        assert s.area.flight_level == 3.5
        assert 0 < s.start_goal.min_distance < s.start_goal.max_distance
        assert s.source.endswith(f"{name}.toml")


def test_dynamic_is_valley_plus_three_aircraft() -> None:
    valley, dyn = load_scenario("valley"), load_scenario("dynamic")
    assert dyn.seed == valley.seed and dyn.terrain == valley.terrain
    assert len(valley.aircraft) == 0 and len(dyn.aircraft) == 3
    for ac in dyn.aircraft:
        assert 1.0 <= ac.speed <= 2.0
        zs = [w[2] for w in ac.waypoints]
        assert min(zs) < 3.5 < max(zs)  # crosses the flight level


def test_load_by_path(tmp_path: Path) -> None:
    s = load_scenario(write(tmp_path, GOOD, "tiny.toml"))
    assert s.terrain.hills.count == 2 and s.seed == 3
    assert load_scenario(str(tmp_path / "tiny.toml")).name == "tiny"


def test_unknown_scenario_lists_known() -> None:
    with pytest.raises(ScenarioError) as e:
        load_scenario("moon")
    msg = str(e.value)
    assert "moon" in msg and all(n in msg for n in ("city", "dynamic", "forest", "valley"))


@pytest.mark.parametrize(
    ("text", "needles"),
    [
        (GOOD.replace("seed = 3\n", ""), ["'seed'", "missing"]),
        (GOOD.replace('name = "tiny"\n', ""), ["'name'", "missing"]),
        (GOOD.replace("count = 2", 'count = "two"'), ["terrain.hills.count", "integer", "str"]),
        (GOOD.replace("count = 2", "count = 2.5"), ["terrain.hills.count", "integer"]),
        (GOOD.replace("size_x = 35.0", 'size_x = "big"'), ["area.size_x", "number"]),
        (GOOD.replace("size_x = 35.0", "size_x = -4.0"), ["area.size_x", "out of range"]),
        (GOOD.replace("count = 2", "count = -1"), ["terrain.hills.count", "out of range"]),
        (GOOD + "height = [9.0, 5.0]\n", ["terrain.hills.height", "min <= max"]),
        (GOOD + "height = [5.0]\n", ["terrain.hills.height", "2 values"]),
        (GOOD + "hieght = [5.0, 6.0]\n", ["terrain.hills.hieght", "unknown field"]),
        (GOOD + "[start_goal]\nmin_distance = 20.0\nmax_distance = 10.0\n",
         ["start_goal.min_distance", "max_distance"]),
        (GOOD + "[[aircraft]]\nspeed = 1.0\n", ["aircraft[0].waypoints", "missing"]),
        (GOOD + "[[aircraft]]\nwaypoints = [[0.0, 0.0]]\n",
         ["aircraft[0].waypoints[0]", "3 values"]),
        (GOOD.replace("seed = 3", "seed = true"), ["'seed'", "integer"]),
        ("terrain = 5\n" + GOOD.replace("[terrain.hills]\ncount = 2\n", ""),
         ["'terrain'", "table"]),
    ],
)
def test_malformed_field_named(tmp_path: Path, text: str, needles: list[str]) -> None:
    with pytest.raises(ScenarioError) as e:
        load_scenario(write(tmp_path, text))
    msg = str(e.value)
    assert msg.startswith("bad.toml"), msg
    for n in needles:
        assert n in msg, (n, msg)


def test_bad_toml_syntax(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError) as e:
        load_scenario(write(tmp_path, GOOD + "oops = = 3\n"))
    msg = str(e.value)
    assert "bad.toml" in msg and "TOML" in msg and "line" in msg


def test_missing_file_and_unknown_base(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario(tmp_path / "nope.toml")
    with pytest.raises(ScenarioError) as e:
        load_scenario(write(tmp_path, 'base = "mars"\n' + GOOD))
    assert "'base'" in str(e.value) and "valley" in str(e.value)


def test_shipped_files_are_commented_data() -> None:
    for p in SCENARIO_DIR.glob("*.toml"):
        assert p.read_text().lstrip().startswith("#"), p
