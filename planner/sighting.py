"""An external sighting: a target reported in one cell by someone outside the swarm (an operator
marking a cell of interest on the mission view, docs/view.md), taken into the swarm's beliefs.

The report is read as a look of the swarm's own sensor that saw the target from straight above:
eq 18 with b = 1 at distance 0, so P_D (``cfg.p_detect``) against the cell's false alarm
probability (``cfg.cell_false_alarm``: a look's P_F shared over its K footprint cells), applied
to every UAV's TPM (everyone hears an operator), then eq 16: the cell's odds grow ~250 times
(0.9 / 0.0036, paper defaults); in paper-2uav at step 0 cell (50, 50) went from 0.004 to 0.47,
the highest of either UAV's map (tests/planner/test_sighting.py). Nothing
else changes: no cell counts as covered (no UAV looked), and a sighting is evidence, not an
engagement, so the swarm still has to go and look (eq 24 draws it up the TPM's gradient; a look
that detects there confirms it, one that sees nothing lowers it again, eq 18).

Pure: numpy on the beliefs passed in, no I/O.
"""

from __future__ import annotations

import numpy as np

from planner.swarm_beliefs import SwarmBeliefs


def take_sighting(beliefs: SwarmBeliefs, cell: tuple[int, int] | np.ndarray) -> None:
    """Every UAV's TPM takes a detection (b = 1, from straight above) at grid ``cell`` (ix, iy),
    then is renormalised (eq 16). A cell outside the grid is a ``ValueError``."""
    at = np.asarray(cell, dtype=np.int64).reshape(1, 2)
    if not bool(beliefs.grid.inside(at)[0]):
        nx, ny = beliefs.grid.shape
        raise ValueError(f"cell {tuple(int(c) for c in at[0])} is outside the {nx}x{ny} grid")
    n = beliefs.n
    beliefs.tpm.apply_looks(
        np.arange(n), [at] * n, [np.array([True])] * n, np.repeat(at, n, axis=0)
    )
    beliefs.tpm.renormalise()
