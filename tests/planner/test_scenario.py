import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from planner.config import ConfigError, PlannerConfig
from planner.scenario import (
    BUILTIN_SCENARIOS,
    START_THREAT_GAP_KM,
    ScenarioError,
    load_scenario,
    parse_scenario,
)

GOOD = """
name = "small"
steps = 20
[uavs]
count = 1
[[uavs.start]]
x_km = 5
y_km = 5
[[targets]]
kind = "unknown_position"
x_km = 50
y_km = 50
value = 1
"""


def test_builtin_scenarios_match_the_paper():
    two = load_scenario("paper-2uav")
    assert two.uav_count == 2 and not two.threats and two.config.n_topo == 1
    assert [(s.x_km, s.y_km) for s in two.uav_starts] == [(10.5, 10.5), (90.5, 90.5)]
    ten = load_scenario("paper-10uav")
    assert ten.uav_count == 10 and len(ten.threats) == 5 and ten.config.max_range_km == 330
    assert len(ten.targets) == 16 and sum(t.value for t in ten.targets) == 42
    assert {t.kind for t in ten.targets} == {
        "unknown_position",
        "known_position",
        "known_speed",
        "known_velocity",
    }
    assert load_scenario("paper-20uav").uav_count == 20
    assert set(BUILTIN_SCENARIOS) == {
        "paper-2uav",
        "paper-10uav",
        "paper-20uav",
        "arduplane-3uav",
        "px4-3uav",
        "swarm-100uav",
        "swarm-500uav",
    }


@pytest.mark.parametrize("count", [100, 500])
def test_the_swarm_scenarios_start_apart_on_the_edges_clear_of_threats(count, tmp_path):
    s = load_scenario(f"swarm-{count}uav")
    assert s.uav_count == count == len(s.uav_starts)
    assert (s.config.grid_nx, s.config.grid_ny, s.config.cell_km) == (200, 200, 1.0)
    assert len(s.targets) == 64 and len(s.threats) == 20 and s.config.max_range_km == 330
    xy = np.array([(u.x_km, u.y_km) for u in s.uav_starts])
    gaps = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1))
    assert gaps[np.triu_indices(count, 1)].min() >= 2.0  # two cells, as random starts keep
    inset = np.minimum(xy, 200 - xy).min(axis=1)
    assert inset.min() >= 5 and inset.max() <= 13  # on the rings near the edges
    clearance = s.config.detection_radius_km + START_THREAT_GAP_KM
    for t in s.threats:
        assert np.hypot(xy[:, 0] - t.x_km, xy[:, 1] - t.y_km).min() > t.radius_km + clearance
    heading = np.radians([u.heading_deg for u in s.uav_starts])  # counter-clockwise from east
    inward = (np.cos(heading) * (100 - xy[:, 0]) + np.sin(heading) * (100 - xy[:, 1])) > 0
    assert inward.all()
    # the file is what its generator writes
    tool = Path(__file__).parents[2] / "tools" / "swarm_scenarios.py"
    subprocess.run([sys.executable, str(tool), str(tmp_path)], check=True, capture_output=True)
    packaged = Path(__file__).parents[2] / "planner" / "scenarios" / f"swarm-{count}uav.toml"
    assert (tmp_path / f"swarm-{count}uav.toml").read_text() == packaged.read_text()


def test_random_starts_are_reproducible_and_safe():
    s = load_scenario("paper-20uav")
    a, b = s.starts_for_seed(4), s.starts_for_seed(4)
    assert a == b and a != s.starts_for_seed(5)
    for start in a:
        for t in s.threats:
            assert (
                (start.x_km - t.x_km) ** 2 + (start.y_km - t.y_km) ** 2
            ) ** 0.5 > t.radius_km + 3


def test_good_file_parses():
    s = parse_scenario(GOOD, "small.toml")
    assert s.steps == 20 and s.uav_count == 1


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (("x_km = 50\ny_km = 50", "x_km = 150\ny_km = 50"), "outside the 100 x 100 km area"),
        (('kind = "unknown_position"', 'kind = "flying"'), "use one of"),
        (("value = 1", 'value = "high"'), "must be a number"),
        (("value = 1", "value = -2"), "value must be > 0"),
        (("count = 1", "count = 2"), "make them agree"),
        (("steps = 20", "steps = 0"), "positive integer"),
        (("[uavs]", "[uavs]\nwingspan = 3"), "unknown key 'wingspan'"),
        (("steps = 20", "steps = 20\n[parameters]\np_detect = 2.0"), "p_detect"),
        (("steps = 20", "steps = 20\n[parameters]\nwarp = 2.0"), "unknown parameter 'warp'"),
        (("steps = 20", "steps = 20 ]]"), "not valid TOML"),
        (
            ("value = 1", "value = 1\n[[threats]]\nx_km = 5\ny_km = 5\nradius_km = 2"),
            "starts inside threats",
        ),
        (
            ("value = 1", "value = 1\n[[threats]]\nx_km = 50\ny_km = 50\nradius_km = -1"),
            "radius_km must be > 0",
        ),
        (("x_km = 50\ny_km = 50", "y_km = 50"), "x_km is missing"),
    ],
)
def test_broken_scenarios_give_one_clear_line(change, message):
    old, new = change
    assert old in GOOD
    with pytest.raises(ScenarioError, match=message) as info:
        parse_scenario(GOOD.replace(old, new, 1), "broken.toml")
    assert "\n" not in str(info.value) and "broken.toml" in str(info.value)


def test_missing_file_names_the_builtins(tmp_path):
    with pytest.raises(ScenarioError, match="neither a built-in"):
        load_scenario(tmp_path / "nope.toml")


#: A scenario giving every number a scenario file can hold outside [parameters]: key -> value.
EVERY_NUMBER = {
    "altitude_m": "500",
    "origin.lat": "-35.3",
    "origin.lon": "149.1",
    "origin.alt_m": "584",
    "uavs.start.x_km": "5",
    "uavs.start.y_km": "5",
    "uavs.start.heading_deg": "45",
    "targets.x_km": "50",
    "targets.y_km": "50",
    "targets.value": "1",
    "targets.speed_mps": "10",
    "targets.heading_rad": "1",
    "threats.x_km": "80",
    "threats.y_km": "80",
    "threats.radius_km": "3",
}


def every_number_scenario(key: str = "", token: str = "") -> str:
    v = {**EVERY_NUMBER, **({key: token} if key else {})}
    return f"""
altitude_m = {v["altitude_m"]}
origin = {{ lat = {v["origin.lat"]}, lon = {v["origin.lon"]}, alt_m = {v["origin.alt_m"]} }}
[uavs]
count = 1
[[uavs.start]]
x_km = {v["uavs.start.x_km"]}
y_km = {v["uavs.start.y_km"]}
heading_deg = {v["uavs.start.heading_deg"]}
[[targets]]
kind = "known_velocity"
x_km = {v["targets.x_km"]}
y_km = {v["targets.y_km"]}
value = {v["targets.value"]}
speed_mps = {v["targets.speed_mps"]}
heading_rad = {v["targets.heading_rad"]}
[[threats]]
x_km = {v["threats.x_km"]}
y_km = {v["threats.y_km"]}
radius_km = {v["threats.radius_km"]}
"""


NON_FINITE = ("inf", "-inf", "nan", "1e400", "-1e400")


@pytest.mark.parametrize("token", NON_FINITE)
@pytest.mark.parametrize("key", sorted(EVERY_NUMBER))
def test_every_number_of_a_scenario_must_be_finite(key, token):
    parse_scenario(every_number_scenario(), "numbers.toml")  # the template itself is good
    with pytest.raises(ScenarioError, match="finite") as info:
        parse_scenario(every_number_scenario(key, token), "numbers.toml")
    message = str(info.value)
    assert "\n" not in message and "numbers.toml" in message and key.split(".")[-1] in message


FLOAT_PARAMETERS = [f.name for f in dataclasses.fields(PlannerConfig) if f.type == "float"]


def test_the_audit_covers_the_float_parameters():
    assert len(FLOAT_PARAMETERS) > 40 and "max_range_km" in FLOAT_PARAMETERS


@pytest.mark.parametrize("token", NON_FINITE)
@pytest.mark.parametrize("name", FLOAT_PARAMETERS)
def test_every_float_parameter_must_be_finite(name, token):
    """``max_range_km = 1e400`` (infinity to TOML) used to lift the range limit silently."""
    text = GOOD.replace("steps = 20", f"steps = 20\n[parameters]\n{name} = {token}")
    with pytest.raises(ScenarioError, match=f"'{name}' must be finite") as info:
        parse_scenario(text, "broken.toml")
    assert "\n" not in str(info.value) and "broken.toml" in str(info.value)


def test_no_range_limit_is_a_left_out_max_range_km():
    assert math.isinf(parse_scenario(GOOD, "small.toml").config.max_range_km)
    text = GOOD.replace("steps = 20", "steps = 20\n[parameters]\nmax_range_km = 1e400")
    with pytest.raises(ScenarioError, match="leave max_range_km out for no range limit"):
        parse_scenario(text, "broken.toml")
    with pytest.raises(ConfigError, match="infinite"):
        PlannerConfig(speed_mps=math.inf)
