"""C_c without a centre when a claim is missing at the deadline (section 3.3.1 has no centre;
``planner.uav_node``): the moves a neighbour whose claim did not arrive may make, and the
choice of a node that must keep clear of them.

A neighbour's *moves* are segments (start, end) in km, flown in the same decision period as
the node's own: a conflict is the two UAVs closer than d_min at any instant of the step
(simultaneous straight moves, ``move_gaps``), so two UAVs that swap cells or cross conflict
though their end cells are apart. A holding UAV's move has its start as its end.

The rule (``choose_under_deadline``), for a node whose turn has come with the claims ``heard``
(points, certain) and the ``missed`` neighbours' possible moves (every candidate move of each,
and holding in place, which a neighbour may do: it is done, boxed in, or under this rule):

1. its first ranked allowed candidate clear of both (d_min from every heard claim, and from
   every missed move at every instant): the node moves there (``avoided``);
2. else its hold, when clear of both: a cell no missed neighbour can come within d_min of
   (``held``);
3. else, squeezed (``squeezed``): a heard claim is certain, a missed move only possible, so
   the options d_min from every heard claim come first, and among them the one keeping the
   most separation from the missed moves; when no option is clear of the heard claims, the
   one keeping the most separation from both (the largest of the smallest gaps). Among equal
   gaps the hold comes first: two nodes that each missed the other's claim and both hold keep
   the separation they have now (e.g. heading at each other, claims lost both ways), then the
   ranking. (Weighing both alike, a node that heard a neighbour claim its own cell held there
   because a neighbour last heard a step ago might reach every other option: paper-10uav
   seed 8, 50 km, 30 % loss, step 103, UAVs 4 and 5 in cell (69, 7).)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.grid import candidate_moves, square_offsets

#: How many steps a neighbour last heard of is still predicted (its reach grows a cell a step).
PREDICT_STEPS = 5


@dataclass(frozen=True)
class DeadlineChoice:
    """What ``choose_under_deadline`` decided: a candidate index, or ``hold``; and which rule."""

    candidate: int  # -1 when holding
    rule: str  # "avoided", "held" or "squeezed"

    @property
    def hold(self) -> bool:
        return self.candidate < 0


def neighbour_moves(
    cell: tuple[int, int], heading: int, age: int, max_turn_deg: float, cell_km: float
) -> np.ndarray:
    """(M, 2, 2) km: the moves (start, end) a neighbour last heard ``age`` steps ago at
    ``cell`` with ``heading`` may make in this step. Heard this step: each of its candidate
    moves, and holding its cell. Heard earlier: it may have come to any cell within ``age``
    moves by now (a move is one cell, any way, or none), and from each of them it may move to
    any cell next to it, or hold: every such move, flown over the step. (Taking every cell
    within ``age + 1`` moves as a point occupied for the whole step instead would put it at
    the node's own cell at the step's start whenever that is within reach of its move: every
    option of the node then looks as bad as holding, and the node holds where the neighbour
    may come.)"""
    here = np.array(cell, dtype=np.int64)
    if age == 0:
        cand, _ = candidate_moves(here[None, :], np.array([heading]), max_turn_deg)
        ends = np.concatenate([cand[0], here[None, :]])
        starts = np.repeat(here[None, :], len(ends), axis=0)
    else:
        reached = here[None, :] + square_offsets(age)  # where it may be at the step's start
        step = square_offsets(1)  # its move from there: any neighbouring cell, or none
        starts = np.repeat(reached, len(step), axis=0)
        ends = starts + np.tile(step, (len(reached), 1))
    return (np.stack([starts, ends], axis=1) + 0.5) * cell_km


def move_gaps(start: np.ndarray, ends: np.ndarray, moves: np.ndarray) -> np.ndarray:
    """(C, M) km: the smallest distance during the step between a UAV flying straight from
    ``start`` (2,) to each of ``ends`` (C, 2) and one flying each of ``moves`` (M, 2, 2), both
    at a constant speed over the same period."""
    rel0 = start[None, None, :] - moves[None, :, 0, :]  # (1, M, 2) at the step's start
    drift = (ends - start)[:, None, :] - (moves[None, :, 1, :] - moves[None, :, 0, :])
    speed2 = (drift**2).sum(axis=2)
    t = np.divide(-(rel0 * drift).sum(axis=2), speed2, out=np.zeros_like(speed2),
                  where=speed2 > 0)  # fmt: skip
    t = np.clip(t, 0.0, 1.0)
    closest = rel0 + t[..., None] * drift
    return np.hypot(closest[..., 0], closest[..., 1])


def choose_under_deadline(
    start: np.ndarray, spots: np.ndarray, ranked: np.ndarray, allowed: np.ndarray,
    heard: np.ndarray, missed: np.ndarray, limit: float,
) -> DeadlineChoice:  # fmt: skip
    """The node's move by the module's rule. ``start`` (2,) km: where it is; ``spots`` (C, 2)
    km: its candidates' centres, ``ranked`` (C,) their order, ``allowed`` (C,) bool; ``heard``
    (H, 2) km: the claims it heard (and the UAVs holding still); ``missed`` (M, 2, 2) km: the
    moves of the neighbours whose claims are missing; ``limit``: d_min (less a rounding
    margin)."""
    ends = np.concatenate([spots, start[None, :]])  # the candidates, then the hold
    certain = np.full(len(ends), np.inf)  # the gaps to the heard claims, then to missed moves
    possible = np.full(len(ends), np.inf)
    if len(heard):
        apart = ends[:, None, :] - heard[None, :, :]
        certain = np.hypot(apart[..., 0], apart[..., 1]).min(axis=1)
    if len(missed):
        possible = move_gaps(start, ends, missed).min(axis=1)
    gap = np.minimum(certain, possible)
    for c in ranked.tolist():
        if allowed[c] and gap[c] >= limit:
            return DeadlineChoice(int(c), "avoided")
    if gap[-1] >= limit:
        return DeadlineChoice(-1, "held")
    options = [-1] + [int(c) for c in ranked.tolist() if allowed[c]]  # the hold first
    clear = [c for c in options if certain[c] >= limit]
    if clear:
        options, gap = clear, possible
    best = max(options, key=lambda c: (gap[c], -options.index(c)))
    return DeadlineChoice(best, "squeezed")
