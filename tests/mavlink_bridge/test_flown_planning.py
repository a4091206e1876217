"""The scenario as the daemon's planner plans it (mavlink_bridge/flown_planning.py), flown
offline: `swarmplan run --as-flown`."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mavlink_bridge.daemon import DaemonOptions
from mavlink_bridge.flown_planning import simulator_planning_scenario
from planner.constraints import segment_clearance
from planner.scenario import load_scenario
from sim_gateway.offline_runner import run_offline


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
    assert flown["planned_with"] == {
        "min_separation_km": 1.0 + options.separation_margin_km,
        "threat_margin_km": margin,
        "home_path_margin_km": margin,
        "home_reserve_steps": scenario.config.home_reserve_steps + options.home_reserve_extra_steps,
    }
    assert flown["min_separation_limit_km"] == 1.0  # judged by the scenario's d_min
    assert flown["violations"] == {"threat": 0, "separation": 0, "turn": 0, "range": 0}
