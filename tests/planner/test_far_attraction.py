"""The far attraction (eqs 23-24 smoothed over ``far_length_km``, ``far_weight`` in eta): the
gradient of the TPM at a UAV's own cell is near zero away from a prior's blob, so without it a
sparse swarm flies past the priors; paper-2uav turns it on (docs/parameters.md)."""

from planner.hapf_aco import HapfAcoPlanner
from planner.scenario import load_scenario, parse_scenario
from sim_gateway.offline_runner import run_offline

ABEAM = """
name = "abeam"
steps = 40
[uavs]
count = 1
[[uavs.start]]
x_km = 20.5
y_km = 20.5
heading_deg = 0
[[targets]]
kind = "known_position"
x_km = 25
y_km = 70
value = 1
"""


def test_the_candidate_heading_for_a_distant_prior_is_pulled_the_most():
    # heading east, a prior's blob 50 km to the north: beyond the footprint and far outside
    # the blob (sigma 5 km), the north-east candidate reads the most of the smoothed field
    scenario = parse_scenario(ABEAM).with_config(far_weight=0.5)
    planner = HapfAcoPlanner(scenario, scenario.starts_for_seed(0), seed=0)
    options = planner.beliefs.move_options()
    share = planner._far_share(options.cells, options.headings, options.feasible)[0]
    heads = list(options.headings[0])
    north_east, east, south_east = heads.index(1), heads.index(0), heads.index(7)
    assert share[north_east] == 1.0
    assert share[north_east] > share[east] > share[south_east] >= 0.0


def test_paper_2uav_engages_more_of_its_targets_with_the_far_attraction():
    # seeds 1-12 (250 steps): engaged 71 without it, 81 with it (seen 70 and 84)
    scenario = load_scenario("paper-2uav")
    assert scenario.config.far_weight > 0
    without = scenario.with_config(far_weight=0.0)

    def engaged(s) -> int:
        return sum(run_offline(s, seed, account=False)["engaged_count"] for seed in range(1, 13))

    assert engaged(scenario) >= engaged(without) + 6
