"""ACOAPF baseline: ant colony optimisation with an artificial potential field (the paper's
section 4.2, Algorithm 2, after its ref. [27]).

The paper defines it by difference from HAPF-ACO: "a distributed ACO algorithm with an improved
transition rule *without considering the range constraint*, and the APF is introduced *without
considering the dynamic updating of the TPM*". So this planner is HAPF-ACO
(``planner.hapf_aco.HapfAcoPlanner`` on ``planner.swarm_beliefs.SwarmBeliefs``: topology
eqs 1-3, probe update eqs 17-18, APF eqs 23-27, pheromone eqs 28-34, transition rules
eqs 35-37 with the N_t escape) with exactly two things taken out, and nothing else changed,
so a comparison isolates what the paper claims they add:

1. **The APF without the TPM's forecast update (eqs 19-22).** The map the potential field
   (eqs 23-27, its far attraction included) and the heuristic information read is initialised
   from the priors (eqs 9-16) and updated by what the sensors see (eqs 17-18), but never
   propagated with the targets' motion models: the field believes the targets stay where the
   prior or the last look put them. Sensing, confirmation and engagement are not the APF:
   they read HAPF-ACO's own TPM (with the forecast) through HAPF-ACO's code, so all three
   planners confirm and engage by one rule (section 3.2.1) and differ only in how they move.
2. **No range term (C_r in eqs 35 and 37).** The planner neither keeps a return slack nor flies
   home; it plans as if L_max were infinite.

Safety constraints still hold: C_m (only turn-limited candidates), C_t (threat segments and the
viability kernel of ``planner.constraints.SafetyModel``) and C_c (cells claimed in priority
order) are the shared code of HAPF-ACO. Range is physics, not planning: a UAV that ignores it
runs out of fuel. **Fair treatment of range (our choice):** when a UAV's distance flown leaves
less than one diagonal step (sqrt(2) cells) of its L_max, it stops flying -- it is reported
``done`` at its last cell, holds there and takes no further part (no looks, no engagements,
no coverage gain, not counted for separation), and it is not ``returned`` because it is not at its
start. So an ACOAPF run never records a range violation, and the cost of ignoring C_r shows up
as UAVs lost before the end of the mission and a low ``returned_count``. With an infinite L_max
(the paper's 2-UAV experiment) this rule never fires.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from planner.engagement import EngagementOutcome
from planner.hapf_aco import HapfAcoPlanner
from planner.planner_interface import StepDecision
from planner.scenario import Scenario, UavStart
from planner.sensor_model import SensorReport
from planner.target_probability_map import TargetProbabilityMaps


class StaticTargetProbabilityMaps(TargetProbabilityMaps):
    """TPMs without the forecast update of eqs 19-22: initialised (eqs 9-16) and probe-updated
    (eqs 17-18, renormalised by eq 16) like HAPF-ACO's, but the targets are believed to stay put."""

    def forecast(self) -> None:
        """No motion model: the maps keep their mass where the last look left it."""
        self.steps += 1


def fuel_exhausted(distance_km: np.ndarray, max_range_km: float, cell_km: float) -> np.ndarray:
    """C_r as physics: True where the next step (up to one diagonal, sqrt(2) cells) could take
    the UAV past L_max. Always False for an unbounded range."""
    if not math.isfinite(max_range_km):
        return np.zeros(np.shape(distance_km), dtype=bool)
    return np.asarray(distance_km) + math.sqrt(2.0) * cell_km > max_range_km + 1e-9


class ApfBeliefs:
    """HAPF-ACO's TPM (``full``: probe and forecast updates, read for sensing, confirmation and
    engagement) with a twin for ACOAPF's potential field (``static``: the same probe updates,
    renormalisation, decay and serviced targets, but no forecast). Every read goes to ``full``;
    ``ApfBeliefs.UPDATES`` are applied to both; ``forecast`` to ``full`` only."""

    UPDATES = ("apply_looks", "decay_unobserved", "renormalise", "remove_target")

    def __init__(self, full: TargetProbabilityMaps, static: StaticTargetProbabilityMaps) -> None:
        self.full = full
        self.static = static

    def __getattr__(self, name: str):
        if name in ApfBeliefs.UPDATES:

            def both(*args, **kwargs):
                getattr(self.static, name)(*args, **kwargs)
                return getattr(self.full, name)(*args, **kwargs)

            return both
        if name in ("full", "static"):  # not set yet (e.g. while unpickling)
            raise AttributeError(name)
        return getattr(self.full, name)


class AcoApfPlanner:
    """ACOAPF (section 4.2, Algorithm 2): HAPF-ACO without the TPM forecast in its potential
    field and without the range term (``planner.planner_interface.SwarmPlanner``). It flies
    a HAPF-ACO planner built on the range-free scenario whose potential field reads the
    forecast-free twin of its TPM (``ApfBeliefs.static``)."""

    algorithm = "acoapf"

    def __init__(self, scenario: Scenario, starts: Sequence[UavStart], seed: int) -> None:
        #: The airframe's real range (fuel), which the planner itself does not consider.
        self.fuel_range_km = scenario.config.max_range_km
        self.hapf_aco = HapfAcoPlanner(
            scenario.with_config(max_range_km=math.inf, home_by_end=False), starts, seed
        )
        beliefs = self.hapf_aco.beliefs
        beliefs.tpm = ApfBeliefs(
            beliefs.tpm, StaticTargetProbabilityMaps(scenario.targets, beliefs.cfg, beliefs.n)
        )  # the potential field reads the twin (``HapfAcoPlanner.field_maps``)
        self.flown_km = np.zeros(beliefs.n)
        self.out_of_fuel = np.zeros(beliefs.n, dtype=bool)

    # the parts of the HAPF-ACO planner it flies, by their usual names (not copies: a
    # checkpoint holds each part once)
    beliefs = property(lambda self: self.hapf_aco.beliefs)
    pheromone = property(lambda self: self.hapf_aco.pheromone)
    cfg = property(lambda self: self.hapf_aco.cfg)
    n = property(lambda self: self.hapf_aco.n)
    grid = property(lambda self: self.hapf_aco.grid)

    def step(
        self,
        cells: np.ndarray,
        headings: np.ndarray,
        reports: Sequence[SensorReport | None],
        engagements: Sequence[EngagementOutcome | None] | None = None,
        active: np.ndarray | None = None,
        positions_km: np.ndarray | None = None,
    ) -> StepDecision:
        """HAPF-ACO's step (section 3.5) with the two omissions above; UAVs out of fuel are
        passed to it as inactive, so they hold and the others keep clear of them (C_c)."""
        cells = np.asarray(cells, dtype=np.int64).reshape(self.n, 2)
        # the beliefs' cells: where the UAVs were at the last step (the step updates them)
        self.flown_km += np.hypot(*((cells - self.beliefs.cells) * self.cfg.cell_km).T)
        self.out_of_fuel |= fuel_exhausted(self.flown_km, self.fuel_range_km, self.cfg.cell_km)
        reachable = (
            np.ones(self.n, dtype=bool) if active is None else np.asarray(active, dtype=bool)
        )
        decision = self.hapf_aco.step(
            cells, headings, reports, engagements, reachable & ~self.out_of_fuel, positions_km
        )
        return StepDecision(
            decision.next_cells,
            decision.next_headings,
            decision.engage & ~self.out_of_fuel,
            decision.done | self.out_of_fuel,
            decision.modes,
        )
