"""The two baselines of section 4.2 (PSO, ACOAPF) fly the same world under the same constraints
as HAPF-ACO (eq 5), and each differs from it exactly where the paper says."""

import json

import numpy as np
import pytest

from planner.acoapf import AcoApfPlanner, StaticTargetProbabilityMaps, fuel_exhausted
from planner.hapf_aco import HapfAcoPlanner
from planner.potential_field import block_masses
from planner.pso import PsoPlanner, PsoSettings
from planner.registry import planner_factory
from planner.scenario import load_scenario
from sim_gateway.offline_runner import run_offline
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
    assert planner_factory("pso") is PsoPlanner and planner_factory("acoapf") is AcoApfPlanner


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


def test_acoapf_field_has_no_forecast_but_its_confirmation_beliefs_have():
    """Algorithm 2: the APF without the TPM's forecast; sensing, confirmation and engagement
    read HAPF-ACO's own TPM (forecast included), one rule for all three planners."""
    scenario = load_scenario("paper-2uav")
    starts = scenario.starts_for_seed(1)
    aco, hapf = AcoApfPlanner(scenario, starts, 1), HapfAcoPlanner(scenario, starts, 1)
    assert isinstance(aco.beliefs.tpm.static, StaticTargetProbabilityMaps)
    field_before = aco.beliefs.tpm.static.existence_map(1)
    cells, headings = aco.beliefs.cells.copy(), aco.beliefs.headings.copy()
    for _ in range(6):  # no looks reach the maps: only the forecast could change them
        for planner in (aco, hapf):
            d = planner.step(cells, headings, [None, None], None)
        cells, headings = d.next_cells, d.next_headings
    assert np.abs(aco.beliefs.tpm.static.existence_map(1) - field_before).max() == 0.0
    # the beliefs that confirm and engage moved with the targets, exactly as HAPF-ACO's did
    assert np.abs(aco.beliefs.tpm.existence_map(1) - field_before).max() > 1e-6
    np.testing.assert_array_equal(
        aco.beliefs.tpm.existence_map(1), hapf.beliefs.tpm.existence_map(1)
    )
    probe = np.array([[8, 15], [45, 50], [80, 70]])
    rows = np.zeros(len(probe), dtype=np.int64)
    np.testing.assert_array_equal(
        aco.beliefs.engage_probability(rows, probe), hapf.beliefs.engage_probability(rows, probe)
    )
    # the potential field reads the forecast-free map
    window = aco.hapf_aco._existence_window()
    around = aco.beliefs.cells[:, None, None, :] + aco.hapf_aco.window_offsets[None]
    np.testing.assert_array_equal(
        window, aco.beliefs.tpm.static.existence_at(np.arange(aco.n)[:, None, None], around)
    )
    # and so does its far attraction (on in paper-2uav): the block masses at a refresh step
    assert aco.cfg.far_weight > 0
    aco.beliefs.k = 2 * aco.cfg.far_refresh_steps
    options = aco.beliefs.move_options()
    aco.hapf_aco._far_share(options.cells, options.headings, options.feasible)
    unsearched = ~aco.beliefs.coverage
    static, full = aco.beliefs.tpm.static, aco.beliefs.tpm.full
    blocks = aco.cfg.far_block_cells
    np.testing.assert_array_equal(
        aco.hapf_aco.far_masses, block_masses(static.maps, static.scale, blocks, unsearched)
    )
    assert not np.array_equal(
        aco.hapf_aco.far_masses, block_masses(full.maps, full.scale, blocks, unsearched)
    )


def test_pso_asks_for_an_engagement_by_hapf_acos_rule_also_on_its_way_home():
    """One engagement rule: a UAV whose track lies within the engage radius with probability
    >= confirm_threshold asks, whatever mode it flies in (PSO used to skip returning UAVs)."""
    scenario = load_scenario("paper-2uav")
    starts = scenario.starts_for_seed(1)
    decisions = {}
    for cls in (PsoPlanner, HapfAcoPlanner):
        planner = cls(scenario, starts, 1)
        cell = planner.beliefs.cells[0].copy()
        for _ in range(8):  # eight detections at UAV 0's own cell: a confirmed target
            planner.beliefs.tpm.apply_looks(
                np.array([0]), [cell[None]], [np.array([True])], cell[None]
            )
        planner.beliefs.tpm.renormalise()
        assert planner.beliefs.engage_probability(np.array([0]), cell[None])[0] >= 0.5
        planner.beliefs.track[0] = cell
        planner.beliefs.track_confirmed[0] = True
        planner.beliefs.returning[0] = True  # flying home (C_r)
        planner.beliefs._update_tracks = lambda *args: None  # keep the track as set
        decisions[cls.algorithm] = planner.step(
            planner.beliefs.cells.copy(), planner.beliefs.headings.copy(), [None, None], None
        )
    assert decisions["hapf-aco"].engage[0]
    assert decisions["pso"].engage[0]


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
    fp = planner.beliefs.footprint
    for p, path_turns in enumerate(turns[0]):
        heading, cell, seen = (
            int(planner.beliefs.headings[0]),
            planner.beliefs.cells[0].copy(),
            set(),
        )
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
