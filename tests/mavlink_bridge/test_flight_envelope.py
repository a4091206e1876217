"""The flight-path layer of the safety envelope settles the UAVs one after the other; when a later
UAV has no safe guided target next to an earlier one, the earlier one's choice is re-opened."""

from __future__ import annotations

import numpy as np

from mavlink_bridge.flight_envelope import FlightEnvelope
from mavlink_bridge.flight_prediction import PlaneModel
from mavlink_bridge.safety_envelope import SafetyEnvelope
from planner.grid import HEADING_STEPS


def test_head_on_pair_both_give_way_when_the_second_alone_cannot(paper10):
    cells = SafetyEnvelope.for_scenario(paper10, 1.0, 1.0)
    grid = cells.grid
    envelope = FlightEnvelope(cells, PlaneModel())
    # two planes 3 km apart on one row, flying at each other, far from every threat; the
    # planner (as if it had not seen the other) sends both straight on
    here = np.array([[40, 60], [43, 60]])
    headings = np.array([0, 4])  # east, west
    proposed = here + HEADING_STEPS[headings]
    choice = envelope.choose(
        grid.centre_km(here), np.array([0.0, np.pi]), np.full(2, 100.0), here, headings,
        proposed, headings, np.full((2, 2), np.nan), np.zeros(2), grid.centre_km(here),
        np.ones(2, dtype=bool), 1.0,
    )  # fmt: skip
    need = paper10.config.min_separation_km + envelope.separation_margin_km
    assert choice.min_separation_km >= need
    # the first plane, settled first, turned too: the second could not get clear on its own
    assert not np.array_equal(choice.next_cells[0], proposed[0])
    assert not np.array_equal(choice.next_cells[1], proposed[1])
    assert (
        choice.overrides["predicted_separation"] == 2 and choice.overrides["predicted_threat"] == 0
    )
