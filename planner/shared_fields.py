"""Fields of the way home lent between the safety models of a swarm
(``planner.constraints.SafetyModel``), so that a UAV that learns of a threat far from its home
does not search its fields again.

A field counts the shortest ways from every cell to a home over a graph of moves, each cell's
moves (their number and lengths) the same in two models but at the cells where the threats
known to one and not the other change them (``changed_cells``). Every cell of a shortest way
is nearer the home than the cell it starts from, so a cell nearer than every changed cell (by
the moves to it with no threats in the way, the least any way can take: ``free_distance``)
has its shortest ways over unchanged cells only, the same ways in both models: its value
in one model's field is its value in the other's, to the bit (a Dijkstra value is the least
sum over its best neighbour's value plus the move, whatever order the search took). A
model that lacks a home's field takes it from another holding it, as far as that reaches.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np

from planner.field_rows import FieldRows, free_distance

#: how far below a threat-free distance a Dijkstra sum of the same moves may round (km; for
#: the counts of moves, whole numbers, it keeps those below the nearest changed cell's)
ROUNDING = 1e-6


def changed_cells(moves: np.ndarray, other: np.ndarray) -> np.ndarray:
    """(K, 2): the cells whose moves differ between two models' move masks (8, nx, ny)."""
    return np.argwhere((moves != other).any(axis=0))


def borrowed_field(
    lenders: Iterable[tuple[FieldRows, Callable[[], np.ndarray]]],
    home: int,
    reach: tuple[float, float],
    ny: int,
    move_lengths: tuple[float, float],
) -> tuple[np.ndarray, float] | None:
    """The field of ``home`` from the first of ``lenders`` (each a model's fields of one kind
    and a function giving the cells where its moves differ from the borrower's) that holds it
    exactly as far as ``reach[0]``, cut to where it is exact for the borrower and to
    ``reach[1]`` (inf beyond; in the store's form, ``FieldRows.cut``), with how far that is;
    None when none does."""
    wanted, most = reach
    for fields, changed in lenders:
        if home not in fields:
            continue
        row = fields.row_of(home)
        exact = min(float(fields.reach[row]), most)
        if exact < wanted:
            continue
        cells = changed()
        if len(cells):
            nearest = free_distance(home, cells[:, 0], cells[:, 1], ny, move_lengths).min()
            exact = min(exact, float(nearest) - ROUNDING)
        if exact < wanted:
            continue
        return fields.cut(row, exact), exact
    return None
