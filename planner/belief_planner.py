"""A planner on the swarm's shared beliefs (``planner.swarm_beliefs.SwarmBeliefs``): the step
every such planner takes, and how the rest of the project finds a planner's beliefs."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from planner.engagement import EngagementOutcome
from planner.planner_interface import StepDecision
from planner.sensor_model import SensorReport
from planner.swarm_beliefs import Hearing, SwarmBeliefs


class BeliefPlanner:
    """A planner on ``SwarmBeliefs`` (``planner.planner_interface.SwarmPlanner``): each step
    observes (``SwarmBeliefs.observe``), decides (``decide``, the planner's own rule) and
    finishes (``SwarmBeliefs.finish_step``). HAPF-ACO and PSO are two."""

    algorithm = ""
    beliefs: SwarmBeliefs

    def step(
        self,
        cells: np.ndarray,
        headings: np.ndarray,
        reports: Sequence[SensorReport | None],
        engagements: Sequence[EngagementOutcome | None] | None = None,
        active: np.ndarray | None = None,
        positions_km: np.ndarray | None = None,
    ) -> StepDecision:
        """One decision step (``planner.planner_interface``, the arguments)."""
        seen = self.beliefs.observe(cells, headings, reports, engagements, active, positions_km)
        decision = self.decide(seen)
        self.beliefs.finish_step(decision)
        return decision

    def decide(self, seen: Hearing) -> StepDecision:
        """The planner's rule: every UAV's move, from the step's beliefs."""
        raise NotImplementedError


def beliefs_of(planner: object) -> SwarmBeliefs | None:
    """The ``SwarmBeliefs`` a planner keeps its beliefs in (its ``beliefs``), or None."""
    beliefs = getattr(planner, "beliefs", None)
    return beliefs if isinstance(beliefs, SwarmBeliefs) else None
