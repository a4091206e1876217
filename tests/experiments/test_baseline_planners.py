"""The two baselines of section 4.2 (PSO, ACOAPF) fly the same world under the same constraints
as HAPF-ACO (eq 5), and each differs from it exactly where the paper says."""

import json

import numpy as np
import pytest

from planner.acoapf import AcoApfPlanner, StaticTargetProbabilityMaps, fuel_exhausted
from planner.hapf_aco import HapfAcoPlanner
from planner.pso import PsoPlanner, PsoSettings
from planner.scenario import load_scenario
from sim_gateway.offline_runner import PLANNERS, run_offline
from swarmplan.cli import main as swarmplan

NO_VIOLATIONS = {"threat": 0, "separation": 0, "turn": 0, "range": 0}


def closest_threat_gap_km(result):
    """Smallest distance from any recorded UAV position to any threat's edge."""
    gaps = [
        np.hypot(
            np.array(u["track_km"])[:, 0] - t["x_km"], np.array(u["track_km"])[:, 1] - t["y_km"]
        ).min()
        - t["radius_km"]
        for u in result["uavs"]
        for t in result["threats"]
    ]
    return min(gaps)


def test_baselines_are_registered_for_swarmplan_run():
    assert PLANNERS["pso"] is PsoPlanner and PLANNERS["acoapf"] is AcoApfPlanner


@pytest.mark.parametrize("algorithm", ["pso", "acoapf"])
def test_baseline_keeps_threat_separation_turn_and_range_constraints(algorithm):
    # Threats unknown until seen, 10 UAVs, and a range short enough to bind within the run.
    scenario = load_scenario("paper-10uav").with_config(max_range_km=60.0)
    near_threat = []
    for seed in (1, 2, 3):
        result = run_offline(scenario, seed, 64, algorithm)
        assert result["violations"] == NO_VIOLATIONS, (algorithm, seed)
        assert result["min_separation_km"] >= scenario.config.min_separation_km
        assert max(u["distance_km"] for u in result["uavs"]) <= 60.0 + 1e-6
        near_threat.append(closest_threat_gap_km(result))
    # not vacuous: some UAV did fly close to a threat zone (within its sensor radius)
    assert min(near_threat) < scenario.config.detection_radius_km


def test_pso_flies_home_under_the_range_constraint_and_acoapf_does_not():
    scenario = load_scenario("paper-2uav").with_config(max_range_km=40.0)
    pso = run_offline(scenario, 4, 60, "pso")
    aco = run_offline(scenario, 4, 60, "acoapf")
    assert pso["violations"] == NO_VIOLATIONS and aco["violations"] == NO_VIOLATIONS
    assert pso["returned_count"] == 2
    # ACOAPF plans without C_r: its UAVs fly their fuel out and stop, away from their starts
    assert aco["returned_count"] == 0
    for uav in aco["uavs"]:
        assert 40.0 - np.sqrt(2) - 1e-6 < uav["distance_km"] <= 40.0 + 1e-6
        assert uav["track_km"][-1] == uav["track_km"][-5]  # holding where the fuel ran out


def test_fuel_rule_stops_within_one_diagonal_step_of_the_range():
    flown = np.array([0.0, 328.0, 328.7, 330.0])
    assert fuel_exhausted(flown, 330.0, 1.0).tolist() == [False, False, True, True]
    assert not fuel_exhausted(flown, np.inf, 1.0).any()


def test_acoapf_tpm_has_no_forecast_but_hapf_aco_has():
    scenario = load_scenario("paper-2uav")
    starts = scenario.starts_for_seed(1)
    planners = {
        "acoapf": AcoApfPlanner(scenario, starts, 1),
        "hapf-aco": HapfAcoPlanner(scenario, starts, 1),
    }
    assert isinstance(planners["acoapf"].tpm, StaticTargetProbabilityMaps)
    moved = {}
    for name, planner in planners.items():
        before = planner.tpm.existence_map(1)
        cells, headings = planner.cells.copy(), planner.headings.copy()
        for _ in range(6):  # no looks reach the maps: only the forecast could change them
            d = planner.step(cells, headings, [None, None], None)
            cells, headings = d.next_cells, d.next_headings
        moved[name] = np.abs(planner.tpm.existence_map(1) - before).max()
    assert moved["acoapf"] == 0.0
    assert moved["hapf-aco"] > 1e-6


def test_pso_fitness_counts_each_footprint_cell_of_a_path_once():
    scenario = load_scenario("paper-2uav")
    settings = PsoSettings(tpm_weight=0.0, terminal_weight=0.0)
    planner = PsoPlanner(scenario, scenario.starts_for_seed(1), 1, settings)
    idx = np.array([0])
    value = planner._window_values(idx, np.zeros((2, 2), dtype=bool))
    terminal = np.zeros((1, (2 * settings.horizon_steps + 1) ** 2))
    turns = np.array([[[0, 0, 0, 0, 0], [1, 1, 1, 1, 1], [-1, 0, 1, 1, -1]]], dtype=float)
    tables = planner._constraint_tables(idx)
    fit, first = planner._fitness(idx, np.array([False]), turns, value, terminal, tables)
    fp = planner.footprint
    for p, path_turns in enumerate(turns[0]):
        heading, cell, seen = int(planner.headings[0]), planner.cells[0].copy(), set()
        for t in path_turns:
            heading = (heading + int(t)) % 8
            cell = (
                cell
                + [(1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1)][heading]
            )
            seen |= {tuple(c) for c in cell + fp if 0 <= c[0] < 100 and 0 <= c[1] < 100}
        assert fit[0, p] == len(seen), p  # nothing searched yet: one per distinct footprint cell
        assert first[0, p] == int(path_turns[0]) + 1


@pytest.mark.parametrize("algorithm", ["pso", "acoapf"])
def test_swarmplan_run_flies_a_baseline_by_name(algorithm, tmp_path, capsys):
    code = swarmplan(["run", "paper-2uav", "--algorithm", algorithm, "--steps", "6", "--json",
                      "--out", str(tmp_path)])  # fmt: skip
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert result["algorithm"] == algorithm and result["steps"] == 6
    assert (tmp_path / "result.json").exists()
