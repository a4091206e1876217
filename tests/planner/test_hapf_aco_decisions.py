"""Decisions of the HAPF-ACO planner on hand-made situations: pursuit of a detection, one UAV
per target, and the engagement only once a target is likely within the engage radius."""

import numpy as np

from planner.hapf_aco import HapfAcoPlanner
from planner.planner_interface import MODES
from planner.scenario import parse_scenario
from planner.sensor_model import SensorReport

TWO_UAVS = """
name = "pursuit"
steps = 40
[uavs]
count = 2
[[uavs.start]]
x_km = 49.5
y_km = 50.5
heading_deg = 0
[[uavs.start]]
x_km = 47.5
y_km = 52.5
heading_deg = 0
[[targets]]
kind = "unknown_position"
x_km = 20
y_km = 80
value = 1
[[targets]]
kind = "unknown_position"
x_km = 40
y_km = 80
value = 1
[[targets]]
kind = "unknown_position"
x_km = 60
y_km = 80
value = 1
[[targets]]
kind = "unknown_position"
x_km = 80
y_km = 80
value = 1
"""


def looks(planner: HapfAcoPlanner, cells: np.ndarray, target: np.ndarray) -> list[SensorReport]:
    """A perfect sensor: each UAV's footprint reports b = 1 exactly at the target's cell."""
    reports = []
    for cell in cells:
        footprint = cell + planner.beliefs.footprint
        footprint = footprint[planner.grid.inside(footprint)]
        reports.append(SensorReport(footprint, (footprint == target).all(axis=1)))
    return reports


def test_the_nearer_uav_pursues_a_detection_and_engages_only_within_the_radius():
    scenario = parse_scenario(TWO_UAVS)
    planner = HapfAcoPlanner(scenario, scenario.starts_for_seed(0), seed=0)
    target = np.array([51, 50])
    cells = np.array([[49, 50], [47, 52]])
    headings = np.array([0, 0])
    engaged_at = None
    for _ in range(30):
        decision = planner.step(cells, headings, looks(planner, cells, target))
        if planner.beliefs.track[0, 0] >= 0 or planner.beliefs.track[1, 0] >= 0:
            # both hear the detections; only the nearer one goes for them
            assert not (planner.beliefs.track[0, 0] >= 0 and planner.beliefs.track[1, 0] >= 0)
        if decision.engage.any():
            who = int(np.flatnonzero(decision.engage)[0])
            engaged_at = cells[who]
            assert np.hypot(*(engaged_at - target)) <= 1.0  # within the 1 km engage radius
            assert MODES[decision.modes[who]] == "engage"
            break
        cells, headings = decision.next_cells, decision.next_headings
    assert engaged_at is not None, "the planner never engaged a target it kept detecting"


def test_false_alarms_scattered_over_the_footprint_start_no_engagement():
    scenario = parse_scenario(TWO_UAVS)
    planner = HapfAcoPlanner(scenario, scenario.starts_for_seed(0), seed=0)
    rng = np.random.default_rng(1)
    cells = np.array([[49, 50], [47, 52]])
    headings = np.array([0, 0])
    for _ in range(30):
        reports = []
        for cell in cells:
            footprint = cell + planner.beliefs.footprint
            footprint = footprint[planner.grid.inside(footprint)]
            reports.append(
                SensorReport(footprint, rng.random(len(footprint)) < scenario.config.p_false)
            )
        decision = planner.step(cells, headings, reports)
        assert not decision.engage.any()
        cells, headings = decision.next_cells, decision.next_headings
