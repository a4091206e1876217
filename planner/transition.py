"""State transition rules (section 3.4, eqs 35-37), batched over UAVs and their candidate cells.

Each function scores the C candidate cells of every UAV (higher is better, ``-inf`` where a
constraint forbids the cell); ``choose`` turns scores into one choice per UAV, and
``claim_cells`` resolves C_c (minimum separation) between UAVs in priority order.

Symbols: Omega -> the candidate axis; theta_j -> ``angle_to``; tau_ij -> ``tau``; eta_ij ->
``eta``; alpha, beta, q_0, lambda -> ``cfg.alpha``, ``cfg.beta``, ``cfg.q0``,
``cfg.env_perception_lambda``; F / F_max -> ``force_norm`` / ``force_max``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.config import PlannerConfig
from planner.topology import pairwise_distances


def angle_to(moves: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """theta_j of eq 35: angle (rad) between each candidate move (N, C, 2) and a direction
    (N, 2)."""
    move_angle = np.arctan2(moves[..., 1], moves[..., 0])
    target_angle = np.arctan2(direction[:, 1], direction[:, 0])[:, None]
    diff = np.abs(np.mod(move_angle - target_angle + np.pi, 2 * np.pi) - np.pi)
    return diff


def deterministic_scores(
    moves: np.ndarray, direction: np.ndarray, allowed: np.ndarray
) -> np.ndarray:
    """Eq 35 with omega_1 = 1: the smallest angle to the potential-field force wins."""
    return np.where(allowed, -angle_to(moves, direction), -np.inf)


def use_deterministic(
    force_norm: np.ndarray, force_max: np.ndarray, q: np.ndarray, cfg: PlannerConfig
) -> np.ndarray:
    """The switch of eqs 35/37: deterministic when q < lambda F / F_max (and the field is not
    flat)."""
    ratio = np.divide(force_norm, force_max, out=np.zeros_like(force_norm), where=force_max > 0)
    return (force_max > cfg.force_floor) & (q < cfg.env_perception_lambda * ratio)


def transition_weights(
    tau: np.ndarray, eta: np.ndarray, allowed: np.ndarray, cfg: PlannerConfig
) -> np.ndarray:
    """Eq 36's numerator tau^alpha eta^beta (0 where the move is not allowed)."""
    weights = np.where(allowed, tau**cfg.alpha * eta**cfg.beta, 0.0)
    if not np.all(np.isfinite(weights)):
        raise FloatingPointError("non-finite transition weight: a belief map holds NaN or inf")
    return weights


def heuristic_choice(
    weights: np.ndarray, q1: np.ndarray, u: np.ndarray, cfg: PlannerConfig
) -> np.ndarray:
    """Eq 37 with omega_1 = 1: argmax of tau^alpha eta^beta when q_1 <= q_0, else a draw S from
    the probabilities of eq 36 (``u`` uniform in [0, 1) per UAV)."""
    best = np.argmax(weights, axis=1)
    total = weights.sum(axis=1, keepdims=True)
    probs = np.divide(
        weights, total, out=np.full_like(weights, 1.0 / weights.shape[1]), where=total > 0
    )
    cumulative = np.cumsum(probs, axis=1)
    drawn = (cumulative < u[:, None] * cumulative[:, -1:]).sum(axis=1)
    drawn = np.where(weights[np.arange(len(weights)), np.minimum(drawn, weights.shape[1] - 1)] > 0,
                     np.minimum(drawn, weights.shape[1] - 1), best)  # fmt: skip
    return np.where(q1 <= cfg.q0, best, drawn)


#: ranks one decision step to spare above any difference of path length home (km)
STEP_RANK_KM = 1e4


def range_scores(
    distance_home_km: np.ndarray, allowed: np.ndarray, time_slack: np.ndarray | None = None
) -> np.ndarray:
    """Eqs 35/37 with omega_2 = 1: once the return slack is spent, the candidate that keeps
    |L_max - L_past(k+1) - D_left(k+1)| smallest among the feasible ones is the one that heads
    home along the shortest safe path.

    With ``time_slack`` (``home_by_end``: the steps to spare after the fewest turn-limited
    moves home, ``SafetyModel.hops_home_at``) the most steps to spare come first and the km
    decide between equals. The km know no heading: a UAV flying away from home along a threat
    took the straight move, the least bad by 0.4 km, step after step, where a turn about was
    two moves shorter (paper-10uav demo seed 27: 17 cells the wrong way, never home)."""
    scores = -distance_home_km
    if time_slack is not None:
        # no bound (+inf): the km alone; no way home (-inf): last
        spare = np.nan_to_num(time_slack, posinf=0.0, neginf=-STEP_RANK_KM)
        scores = scores + STEP_RANK_KM * spare
    return np.where(allowed, scores, -np.inf)


def claim_order(allowed: np.ndarray) -> np.ndarray:
    """C_c's priority: the most constrained UAV first (fewest allowed cells), then the lower
    index. Every UAV can compute its own key (``claim_priority``), so a swarm without a centre
    resolves its claims in the same order (``planner.uav_node``)."""
    n = len(allowed)
    return np.lexsort((np.arange(n), allowed.sum(axis=1)))


def claim_priority(allowed_count: int, uav: int, n_uavs: int) -> int:
    """The place of a UAV with ``allowed_count`` allowed cells in ``claim_order`` as one
    number (smaller claims first)."""
    return allowed_count * n_uavs + uav


@dataclass
class ClaimBoard:
    """The claims of one step as one claimant knows them (``claim_cells`` knows them all):
    every UAV's ranked candidates, their centres and which are allowed; what has been claimed
    so far (NaN: not yet); who senses whom."""

    ranked: np.ndarray  # (N, C) candidate indices, the UAV's preference first
    allowed: np.ndarray  # (N, C) bool
    spots: np.ndarray  # (N, C, 2) km, candidate centres
    claimed: np.ndarray  # (N, 2) km, the claimed (or held) position, NaN when unknown
    choice: np.ndarray  # (N,) int, chosen candidate index
    senses: np.ndarray  # (N, N) bool
    movers: np.ndarray  # (N,) bool
    limit: float  # d_min less a rounding margin


def claim_board(
    ranked: np.ndarray,
    candidates: np.ndarray,
    allowed: np.ndarray,
    positions_km: np.ndarray,
    movers: np.ndarray,
    cell_km: float,
    min_separation_km: float,
    sense_km: float,
) -> ClaimBoard:
    """The board before any claim: the UAVs that hold still hold their positions."""
    n = len(ranked)
    claimed = np.full((n, 2), np.nan)
    claimed[~movers] = positions_km[~movers]
    senses = pairwise_distances(positions_km) <= sense_km
    np.fill_diagonal(senses, False)
    return ClaimBoard(
        ranked, allowed, (candidates + 0.5) * cell_km, claimed, ranked[:, 0].copy(), senses,
        movers, min_separation_km - 1e-9,
    )  # fmt: skip


def claim_cells(
    ranked: np.ndarray,
    candidates: np.ndarray,
    allowed: np.ndarray,
    positions_km: np.ndarray,
    movers: np.ndarray,
    cell_km: float,
    min_separation_km: float,
    sense_km: float,
) -> np.ndarray:
    """C_c: every moving UAV, in ``claim_order``, takes the first of its ranked candidates that
    keeps ``min_separation_km`` from the cells already claimed by UAVs it can sense (within
    ``sense_km``) and from the UAVs that hold still (``claim_next``). Returns the chosen
    candidate index per UAV (its first choice when nothing satisfies the constraint, so the
    metrics see the breach)."""
    board = claim_board(
        ranked, candidates, allowed, positions_km, movers, cell_km, min_separation_km, sense_km
    )
    order = claim_order(allowed)
    for i in order[movers[order]].tolist():
        claim_next(i, board)
    return board.choice


def claim_next(i: int, board: ClaimBoard) -> int | None:
    """UAV ``i``'s claim on ``board`` (in place): its first ranked candidate separated from the
    claims it senses; failing that, a swap with one blocker (``_make_room``). Returns the UAV
    it moved to make room, or None."""
    b = board
    others = b.claimed[b.senses[i] & ~np.isnan(b.claimed[:, 0])]
    spots_i = b.spots[i]
    if len(others):  # which of the UAV's candidates keep d_min from every claimed cell
        d = np.hypot(*(others[:, None, :] - spots_i[None, :, :]).transpose(2, 0, 1))
        separated = (d.min(axis=0) >= b.limit).tolist()
    else:
        separated = [True] * spots_i.shape[0]
    allowed_i, first = b.allowed[i].tolist(), int(b.ranked[i, 0])
    for c in b.ranked[i].tolist():
        if not allowed_i[c] and c != first:
            continue
        if separated[c]:
            b.choice[i] = c
            b.claimed[i] = spots_i[c]
            return None
    moved = _make_room(i, b)
    b.claimed[i] = spots_i[b.choice[i]]
    return moved


def _make_room(i: int, b: ClaimBoard) -> int | None:
    """UAV ``i`` found every allowed candidate within d_min of a claimed cell: where exactly one
    UAV claimed before it blocks one of them, move that UAV to another of its allowed
    candidates that stays separated from everyone else (and from ``i`` there), and give ``i``
    the freed cell. ``choice`` and ``claimed`` are updated in place; when no such swap exists
    they are left as they are (``i`` keeps its first choice and the breach is seen). A UAV
    holding still (not in ``movers``) is never moved. Returns the UAV moved, or None."""
    has = ~np.isnan(b.claimed[:, 0])
    for c in b.ranked[i].tolist():
        if not b.allowed[i, c]:
            continue
        spot = b.spots[i, c]
        near = np.hypot(*(b.claimed - spot).T) < b.limit
        blockers = np.flatnonzero(has & b.senses[i] & near)
        if len(blockers) != 1 or not b.movers[blockers[0]]:
            continue
        j = int(blockers[0])
        for cj in b.ranked[j].tolist():
            if cj == b.choice[j] or not b.allowed[j, cj]:
                continue
            alt = b.spots[j, cj]
            rest = has & b.senses[j]
            rest[j] = False
            apart = np.hypot(*(b.claimed[rest] - alt).T)
            if (apart >= b.limit).all() and np.hypot(*(alt - spot)) >= b.limit:
                b.choice[j], b.claimed[j] = cj, alt
                b.choice[i] = c
                return j
    return None
