"""What a swarm planner is to the rest of the project: the offline runner, the daemon, the
experiments and the mission view call nothing else of it.

A planner decides, once per decision step, the next cell of every UAV of the swarm (batched:
one object plans all N UAVs, each with its own beliefs). It is built as
``factory(scenario, starts, seed)`` (:data:`PlannerFactory`: a class whose ``__init__`` takes
these is one) and then called once per step:

``step(cells, headings, reports, engagements, active, positions_km) -> StepDecision``

=============== ===================================================================================
argument        what it is
=============== ===================================================================================
``cells``       (N, 2) int, the grid cell each UAV is in now (telemetry, or the offline world)
``headings``    (N,) int, each UAV's heading index 0-7 (``planner.grid.HEADING_STEPS``)
``reports``     N sensor looks (``planner.sensor_model.SensorReport``) or None (no look)
``engagements`` N outcomes of the engagements requested at the previous step, or None
``active``      (N,) bool, the UAVs that can be reached this step (None: all); an inactive UAV
                holds and takes no part
``positions_km`` (N, 2) where the UAVs measure themselves (a plane is rarely at its cell's
                centre), or None (the cell centres)
=============== ===================================================================================

The decision (:class:`StepDecision`) must keep the paper's hard constraints (eq 5: turn C_m,
threats C_t, range with return C_r, separation C_c); ``planner.swarm_beliefs.SwarmBeliefs``
holds the paper's shared building blocks that give them (``move_options``, ``claim``, ...) and
the beliefs (TPM, coverage, tracks), so a planner of one's own decides only. A planner that
keeps its beliefs in a ``SwarmBeliefs`` exposes it as ``beliefs``: the per-target account, the
live view's belief layers and the daemon's planner facts read it (a planner without one flies
all the same, without those).

A planner of one's own is registered by name with a Python entry point in the group
``swarmplan.planners`` (``planner.registry``); docs/architecture.md has an example.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from planner.engagement import EngagementOutcome
from planner.scenario import Scenario, UavStart
from planner.sensor_model import SensorReport

#: Why a UAV chose its move (reported per step, for analysis and figures).
MODES = ("hold", "return", "engage", "escape", "deterministic", "heuristic")


@dataclass(frozen=True)
class StepDecision:
    """What a planner decided at one step, for every UAV."""

    next_cells: np.ndarray  # (N, 2) int
    next_headings: np.ndarray  # (N,) int
    engage: np.ndarray  # (N,) bool: request an engagement now, at the current position
    done: np.ndarray  # (N,) bool: back home (or finished); hold
    modes: np.ndarray  # (N,) int index into MODES


@runtime_checkable
class SwarmPlanner(Protocol):
    """A planner of the whole swarm (see the module's docstring)."""

    #: the name users give on the command line (``swarmplan run --algorithm NAME``)
    algorithm: str

    def step(
        self,
        cells: np.ndarray,
        headings: np.ndarray,
        reports: Sequence[SensorReport | None],
        engagements: Sequence[EngagementOutcome | None] | None = None,
        active: np.ndarray | None = None,
        positions_km: np.ndarray | None = None,
    ) -> StepDecision: ...


#: Builds a planner for one mission: ``factory(scenario, starts, seed)``.
PlannerFactory = Callable[[Scenario, Sequence[UavStart], int], SwarmPlanner]

