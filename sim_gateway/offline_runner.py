"""The offline runner: world + UAV kinematics (one cell per step) + a planner, in-process, no
sockets. It is the fast path for experiments; the MAVLink end-to-end run flies the same planner.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from planner.engagement import EngagementOutcome
from planner.grid import Grid, heading_of_angle
from planner.metrics import MissionRecorder
from planner.pursuit_log import PursuitLog
from planner.registry import planner_factory
from planner.scenario import Scenario
from sim_gateway.target_account import TargetAccount, account_of
from sim_gateway.world import World


@dataclass(frozen=True)
class OfflineStep:
    """What one offline decision step did, for an observer (the mission view's recorder):
    read it, never change it. ``decision`` is None for the final record (no decision)."""

    step: int
    positions_km: np.ndarray  # (N, 2) cell centres at the decision instant
    headings: np.ndarray  # (N,) heading indices
    decision: object | None  # the planner's StepDecision
    engagements: list[tuple[int, EngagementOutcome]]  # (UAV, outcome) requested this step
    coverage: float  # J_E so far
    truth: np.ndarray  # (T, 4) target id, x_km, y_km, alive (1/0), before the world moves on
    planner: object


def run_offline(
    scenario: Scenario,
    seed: int,
    steps: int | None = None,
    algorithm: str = "hapf-aco",
    progress: Callable[[int], None] | None = None,
    account: bool = True,
    observer: Callable[[OfflineStep], None] | None = None,
    planning: Scenario | None = None,
) -> dict:
    """Fly ``scenario`` for ``steps`` decision steps with one seed and the planner named
    ``algorithm`` (``planner.registry``); returns the result dict,
    with the per-target account (``sim_gateway.target_account``) unless ``account`` is False
    (the flight is the same either way: the account only reads). ``observer`` gets an
    ``OfflineStep`` after every decision step and one for the end (the mission view's replay).
    ``planning``: the scenario the planner plans with, when not ``scenario`` itself (the
    daemon's margins, ``swarmplan run --as-flown``); the world and the recorder keep
    ``scenario``'s limits."""
    started = time.perf_counter()
    cfg = scenario.config
    steps = scenario.steps if steps is None else steps
    scenario = dataclasses.replace(scenario, steps=steps)  # the planner's last step is this run's
    grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
    starts = scenario.starts_for_seed(seed)
    world = World(scenario, seed)
    planned = scenario if planning is None else dataclasses.replace(planning, steps=steps)
    planner = planner_factory(algorithm)(planned, starts, seed)
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
        recorder.record_modes(decision.modes)
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
        if observer is not None:
            record = _observed(k, positions, headings, decision, outcomes, recorder, world, planner)
            observer(record)
        cells, headings, done = decision.next_cells, decision.next_headings, decision.done
        world.step()
        recorder.record_step(grid.centre_km(cells), planned_km=grid.centre_km(cells), done=done)
        if progress is not None:
            progress(k + 1)
    if observer is not None:
        positions = grid.centre_km(cells)
        observer(_observed(steps, positions, headings, None, [None] * len(starts), recorder, world,
                           planner))  # fmt: skip
    extra: dict = {"planned_with": planned.config.changed_from(cfg)}
    if truth is not None and log is not None:
        extra["target_account"] = account_of(truth.truth(), log.facts())
    return recorder.result(seed, algorithm, time.perf_counter() - started, extra=extra)


def _observed(
    k: int,
    positions: np.ndarray,
    headings: np.ndarray,
    decision: object | None,
    outcomes: list[EngagementOutcome | None],
    recorder: MissionRecorder,
    world: World,
    planner: object,
) -> OfflineStep:
    truth = np.column_stack([world.target_ids, world.positions, world.alive.astype(float)]).astype(
        float
    )
    return OfflineStep(
        step=k,
        positions_km=positions.copy(),
        headings=np.array(headings, copy=True),
        decision=decision,
        engagements=[(i, o) for i, o in enumerate(outcomes) if o is not None],
        coverage=recorder.coverage_curve[-1] if recorder.coverage_curve else 0.0,
        truth=truth,
        planner=planner,
    )
