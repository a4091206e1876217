"""The candidate moves of every UAV and which of them the hard constraints of eq 5 allow.

For each UAV: the turn-limited candidate cells Omega (C_m, ``planner.grid.candidate_moves``),
whether the move is threat-safe and viable (C_t and the area edge,
``planner.constraints.SafetyModel.move_allowed``), and the range slack after it (C_r):
``L_max - (L_past + step + D_left + reserve)``, with D_left the shortest threat-avoiding path
home (``SafetyModel.distance_home_km``). This is the constraint part of HAPF-ACO's decision
(section 3.4), written as one pure function so planners that choose differently (the PSO
baseline) share it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from planner.config import PlannerConfig
from planner.constraints import SafetyModel
from planner.grid import HEADING_LENGTHS, Grid, candidate_moves


@dataclass(frozen=True)
class MoveOptions:
    """Candidate moves (N UAVs x C candidates) and what the constraints say about them."""

    cells: np.ndarray  # (N, C, 2) int, candidate next cells
    headings: np.ndarray  # (N, C) int, heading after the move
    moves: np.ndarray  # (N, C, 2) float, move vectors in cells
    step_km: np.ndarray  # (N, C) leg length
    home_km: np.ndarray  # (N, C) D_left(k+1): shortest safe path home from the candidate
    slack_km: np.ndarray  # (N, C) range slack after the move (inf when L_max is)
    time_slack: np.ndarray  # (N, C) decision steps to spare to be home by the last step (or inf)
    feasible: np.ndarray  # (N, C) bool: allowed and in range (safety only if range cannot be kept)
    #: (N, C) bool: allowed and in range, the time slack aside (``home_by_end`` is a goal that
    #: gives way to separation: a late move home beats two UAVs in one cell)
    safe: np.ndarray
    freedom: np.ndarray  # (N, C) int: allowed moves after this one (``SafetyModel.freedom``)


def feasible_moves(
    cells: np.ndarray,
    headings: np.ndarray,
    distance_km: np.ndarray,
    home_flat: tuple[int, ...],
    known_threats: np.ndarray,
    safety_model: Callable[[np.ndarray], SafetyModel],
    cfg: PlannerConfig,
    grid: Grid,
    steps_left: int | None = None,
) -> MoveOptions:
    """Eq 5's C_m, C_t and C_r over the candidate set Omega of eqs 35-37, for N UAVs.

    ``known_threats[i]`` (N, T) bool says which threats UAV i knows; ``safety_model(known)``
    returns the (cached) model of one such set, shared by every UAV that knows the same
    threats. ``distance_km`` is L_past and ``home_flat`` every UAV's home cell (flat index).
    """
    cand, cand_head = candidate_moves(cells, headings, cfg.max_turn_deg)
    moves = (cand - cells[:, None, :]).astype(float)
    step_km = HEADING_LENGTHS[cand_head] * cfg.cell_km
    allowed = np.zeros(cand_head.shape, dtype=bool)
    home_km = np.zeros(cand_head.shape)
    freedom = np.zeros(cand_head.shape, dtype=np.int64)
    hops = np.zeros(cand_head.shape)
    cx = np.minimum(np.maximum(cand[..., 0], 0), grid.nx - 1)  # clipped into the area
    cy = np.minimum(np.maximum(cand[..., 1], 0), grid.ny - 1)
    # the steps a UAV has for the way home: the steps left but the reserve (home_by_end)
    spare = None if steps_left is None else steps_left - cfg.home_reserve_steps
    for known, members in threat_groups(known_threats):
        model = safety_model(known)
        here = np.broadcast_to(cells[members][:, None, :], cand[members].shape)
        allowed[members] = model.move_allowed(here, cand_head[members])
        freedom[members] = model.freedom[cand_head[members], cx[members], cy[members]]
        homes = np.asarray(home_flat)[members]  # fields computed once per (model, home)
        home_km[members] = model.distances_home_at(homes, cx[members], cy[members])
        if spare is not None:
            hops[members] = model.hops_home_at(
                homes, cx[members], cy[members], cand_head[members], within=spare
            )
    home_km = np.where(grid.inside(cand), home_km, np.inf)
    if np.isfinite(cfg.max_range_km):
        slack = cfg.max_range_km - (
            distance_km[:, None] + step_km + home_km + cfg.return_reserve_km
        )
    else:
        slack = np.full(home_km.shape, np.inf)
    slack = np.where(np.isfinite(home_km), slack, -np.inf)
    if spare is None:
        time_slack = np.full(home_km.shape, np.inf)
    else:
        time_slack = np.where(np.isfinite(home_km), spare - hops, -np.inf)
    safe = allowed & (slack >= 0)
    # If range cannot be kept (only when the start is boxed in), keep safety only.
    safe = np.where(safe.any(axis=1, keepdims=True), safe, allowed)
    feasible = safe & (time_slack >= 0)
    feasible = np.where(feasible.any(axis=1, keepdims=True), feasible, safe)  # late: still safe
    return MoveOptions(
        cand, cand_head, moves, step_km, home_km, slack, time_slack, feasible, safe, freedom
    )


def threat_groups(known_threats: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The distinct rows of ``known_threats`` (N, T) bool, each with the UAVs (indices) that
    have it, in order of first appearance (a dictionary on the rows' bytes: the sets change
    rarely and N is small, so this beats sorting the rows)."""
    groups: dict[bytes, list[int]] = {}
    for i, row in enumerate(known_threats):
        groups.setdefault(row.tobytes(), []).append(i)
    return [(known_threats[m[0]], np.array(m, dtype=np.int64)) for m in groups.values()]
