"""An external sighting (an operator's mark, planner/sighting.py) taken in by every UAV's TPM as
a detection from straight above: eq 18 with P_D against the cell's false alarm probability."""

import numpy as np
import pytest

from planner.hapf_aco import HapfAcoPlanner
from planner.scenario import load_scenario
from planner.sensor_model import bayes_update
from planner.sighting import take_sighting


def planner():
    scenario = load_scenario("paper-2uav")
    return HapfAcoPlanner(scenario, scenario.starts_for_seed(1), 1)


def test_a_sighting_raises_every_uavs_belief_to_the_eq18_detection():
    p = planner()
    beliefs, cfg = p.beliefs, p.beliefs.cfg
    cell = (50, 50)
    before = [beliefs.tpm.existence_map(i).copy() for i in range(beliefs.n)]
    counts = beliefs.tpm.counts.copy()
    take_sighting(beliefs, cell)
    for i in range(beliefs.n):
        after = beliefs.tpm.existence_map(i)
        prior = before[i][cell]
        # one look that saw a target from straight above (eq 18 on the cell's existence); each
        # target layer takes it on its own and is renormalised (eq 16), which keeps the cell
        # within 10 % below that value
        seen = float(
            bayes_update(np.array(prior), np.array(True), cfg.p_detect, cfg.cell_false_alarm)
        )
        assert 0.9 * seen < after[cell] <= seen
        assert after[cell] > 50 * prior
        assert np.unravel_index(after.argmax(), after.shape) == cell  # the likeliest cell now
        assert not beliefs.coverage[i].any()  # nobody looked: nothing counts as searched
    # eq 16: each layer still holds its targets at large
    assert np.allclose(beliefs.tpm.scale * beliefs.tpm.totals, counts)


def test_the_swarm_plans_on_with_a_sighting_and_refuses_a_cell_off_the_grid():
    p = planner()
    with pytest.raises(ValueError, match="outside the 100x100 grid"):
        take_sighting(p.beliefs, (100, 3))
    with pytest.raises(ValueError, match="outside"):
        take_sighting(p.beliefs, (-1, 3))
    take_sighting(p.beliefs, (12, 14))
    cells, headings = p.beliefs.cells.copy(), p.beliefs.headings.copy()
    decision = p.step(cells, headings, [None, None])
    assert np.asarray(decision.next_cells).shape == (2, 2)
