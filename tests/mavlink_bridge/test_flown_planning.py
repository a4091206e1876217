"""The scenario as the daemon's planner plans it (mavlink_bridge/mission/flown_planning.py), flown
offline: `swarmplan run --as-flown`."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mavlink_bridge.mission.daemon import DaemonOptions
from planner.constraints import segment_clearance
from planner.metrics import format_summary
from planner.scenario import load_scenario
from sim_gateway.offline_runner import run_offline
from swarmplan.as_flown import simulator_planning_scenario


def closest_leg_to_a_threat(result: dict, scenario) -> float:
    """km from the nearest threat circle of the planned legs of every UAV (negative inside)."""
    xy = np.array([[t.x_km, t.y_km] for t in scenario.threats])
    radius = np.array([t.radius_km for t in scenario.threats])
    return min(
        float(segment_clearance(np.array(a), np.array(b), xy, radius))
        for u in result["uavs"]
        for a, b in zip(u["planned_km"][:-1], u["planned_km"][1:], strict=True)
    )


@pytest.mark.parametrize("seed", [2, 5])
def test_an_as_flown_run_plans_every_leg_the_flight_margin_clear_of_known_threats(seed):
    """With the threats known from the start, the as-flown planner keeps every leg the flight
    envelope's clearance from them (2.39 km for the simulator's plane: its loiter circle judged
    out to a loiter diameter, plus 0.25 km), where the paper's grid UAVs fly along their edge;
    violations are still judged by the scenario's own limits."""
    scenario = dataclasses.replace(load_scenario("paper-10uav"), threats_known=True)
    planning = simulator_planning_scenario(scenario, 100)
    margin = planning.config.threat_margin_km
    assert margin == pytest.approx(2.39, abs=0.01)
    flown = run_offline(scenario, seed, 100, planning=planning, account=False)
    paper = run_offline(scenario, seed, 100, account=False)
    assert closest_leg_to_a_threat(flown, scenario) >= margin
    assert closest_leg_to_a_threat(paper, scenario) < 1.0
    assert paper["planned_with"] == {}
    options = DaemonOptions(connect=[])
    # the simulator's plane circles on ~1.07 km: the separation margin is the 1 km it is capped at
    assert flown["planned_with"] == {
        "min_separation_km": 1.0 + 1.0,
        "separation_sense_km": 1.0 + 1.0 + 2 * np.sqrt(2),
        "threat_margin_km": margin,
        "home_path_margin_km": margin,
        "home_reserve_steps": scenario.config.home_reserve_steps + options.home_reserve_extra_steps,
    }
    assert flown["min_separation_limit_km"] == 1.0  # judged by the scenario's d_min
    assert flown["violations"] == {"threat": 0, "separation": 0, "turn": 0, "range": 0}


def test_two_uavs_planned_as_flown_that_meet_head_on_keep_apart():
    """paper-10uav seed 11 planned as flown: UAVs 5 and 9 fly one diagonal towards each other
    at step 223, 2.83 km apart. Sensing each other only within 3 km with the planned d_min of
    2 km, the second to claim had no move left 2 km from the first's cell and both flew into
    one cell at step 224. Seen from d_min + 2 diagonal cells on, they keep apart."""
    scenario = load_scenario("paper-10uav")
    planning = simulator_planning_scenario(scenario)
    assert planning.config.separation_sense_km == pytest.approx(2.0 + 2 * np.sqrt(2))
    result = run_offline(scenario, 11, planning=planning, account=False)
    assert result["min_separation_km"] >= scenario.config.min_separation_km
    assert result["violations"] == {"threat": 0, "separation": 0, "turn": 0, "range": 0}


def test_a_mission_too_short_to_go_out_and_back_says_so():
    """px4-3uav flown as 7 steps stays at home: with home_by_end, the way home and the steps
    kept in reserve (3, and the daemon's 3 more) leave no time to search, and nothing said why.
    Every UAV turning home at the first step is now said; 16 steps search."""
    scenario = load_scenario("px4-3uav")
    assert scenario.config.home_by_end
    results = {}
    for steps in (7, 16):
        planning = simulator_planning_scenario(scenario, steps)
        results[steps] = run_offline(scenario, 1, steps, account=False, planning=planning)
    short, long = results[7], results[16]
    assert short["turned_home_at_start"] and short["engaged_count"] == 0
    assert "every UAV turned home at the first step" in format_summary(short)
    assert not long["turned_home_at_start"] and long["engaged_count"] >= 1
    assert "turned home" not in format_summary(long)
