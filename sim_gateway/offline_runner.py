"""The offline runner: world + UAV kinematics (one cell per step) + a planner, in-process, no
sockets. It is the fast path for experiments; the MAVLink end-to-end run flies the same planner.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from planner.acoapf import AcoApfPlanner
from planner.engagement import EngagementOutcome
from planner.grid import Grid, heading_of_angle
from planner.hapf_aco import HapfAcoPlanner
from planner.metrics import MissionRecorder
from planner.pso import PsoPlanner
from planner.pursuit_log import PursuitLog
from planner.scenario import Scenario
from sim_gateway.target_account import TargetAccount, account_of
from sim_gateway.world import World

#: Planners by the name users give on the command line.
PLANNERS: dict[str, Callable] = {
    "hapf-aco": HapfAcoPlanner,
    "acoapf": AcoApfPlanner,  # baseline, section 4.2 Algorithm 2
    "pso": PsoPlanner,  # baseline, section 4.2 Algorithm 1
}


def run_offline(
    scenario: Scenario,
    seed: int,
    steps: int | None = None,
    algorithm: str = "hapf-aco",
    progress: Callable[[int], None] | None = None,
    account: bool = True,
) -> dict:
    """Fly ``scenario`` for ``steps`` decision steps with one seed; returns the result dict,
    with the per-target account (``sim_gateway.target_account``) unless ``account`` is False
    (the flight is the same either way: the account only reads)."""
    started = time.perf_counter()
    cfg = scenario.config
    steps = scenario.steps if steps is None else steps
    grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
    starts = scenario.starts_for_seed(seed)
    world = World(scenario, seed)
    planner = PLANNERS[algorithm](scenario, starts, seed)
    recorder = MissionRecorder(scenario, starts)
    truth = TargetAccount(world) if account else None  # beside the planner, never passed to it
    log = PursuitLog().attach(planner) if account else None  # the planner's facts, read-only
    cells = grid.cell_of(np.array([[s.x_km, s.y_km] for s in starts]))
    headings = heading_of_angle(np.radians([s.heading_deg for s in starts]))
    done = np.zeros(len(starts), dtype=bool)
    outcomes: list[EngagementOutcome | None] = [None] * len(starts)
    recorder.record_step(grid.centre_km(cells), planned_km=grid.centre_km(cells))
    for k in range(steps):
        positions = grid.centre_km(cells)
        looks = world.sense(positions)
        reports = [None if done[i] else looks[i] for i in range(len(starts))]
        if truth is not None:
            truth.observe(k, positions, ~done, reports)
        decision = planner.step(cells, headings, reports, outcomes)
        outcomes = [None] * len(starts)
        for i in np.flatnonzero(decision.engage):
            outcome = world.engage(positions[i], k)
            outcomes[i] = outcome
            if truth is not None:
                truth.record_engagement(k, int(i), outcome)
            if outcome.success:
                recorder.record_engagement(k, int(i), outcome.target_id, outcome.value)
            else:
                recorder.record_engagement_miss()
        cells, headings, done = decision.next_cells, decision.next_headings, decision.done
        world.step()
        recorder.record_step(grid.centre_km(cells), planned_km=grid.centre_km(cells), done=done)
        if progress is not None:
            progress(k + 1)
    extra = None
    if truth is not None and log is not None:
        extra = {"target_account": account_of(truth.truth(), log.facts())}
    return recorder.result(seed, algorithm, time.perf_counter() - started, extra=extra)
