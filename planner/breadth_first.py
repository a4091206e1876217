"""Breadth-first counts of moves over a graph whose nodes have at most a few neighbours each,
kept as a table (``neighbours[node]``: the nodes one move away, padded with ``len(table)``).

The turn-limited way home (``planner.constraints.SafetyModel.hops_home_at``) counts moves over
8 x cells (heading, cell) states with one move per allowed turn: scipy's Dijkstra over the same
graph as a sparse matrix gives the same counts (whole numbers, sums of ones, exact in float64)
through a heap, about 190 ns a state reached on 200 x 200 cells; the level-by-level search
here, a few numpy calls a level, took a fifth of that, and the table a third of the sparse
matrix's memory (``tests/planner/test_safety_fields.py`` checks the counts are the same).
"""

from __future__ import annotations

import numpy as np


def neighbour_table(nodes: int, width: int) -> np.ndarray:
    """An empty table of ``nodes`` rows of ``width`` neighbours each (every one the padding
    ``nodes``, which stands for none), to be filled by the caller."""
    return np.full((nodes, width), nodes, dtype=np.int32)


def move_counts(neighbours: np.ndarray, sources: np.ndarray, limit: float) -> np.ndarray:
    """(nodes,) float64: the fewest moves from any of ``sources`` to each node over
    ``neighbours`` (a ``neighbour_table``), counted as far as ``limit`` moves (inf beyond, and
    where no way is): what ``scipy.sparse.csgraph.dijkstra(graph, indices=sources,
    min_only=True, limit=limit)`` gives for the graph of the table with every move one."""
    nodes = len(neighbours)
    counts = np.full(nodes + 1, np.inf)
    counts[nodes] = -1.0  # the padding: never reached
    order = np.empty(nodes + 1, dtype=np.int64)  # scratch: to keep one of each node reached
    frontier = np.unique(np.asarray(sources, dtype=np.int64))
    counts[frontier] = 0.0
    level = 0
    while len(frontier) and level + 1 <= limit:
        level += 1
        reached = neighbours[frontier].ravel()
        reached = reached[counts[reached] == np.inf]
        if not len(reached):
            break
        counts[reached] = level
        # each node once: the last of its places in ``reached`` writes ``order``
        places = np.arange(len(reached))
        order[reached] = places
        frontier = reached[order[reached] == places]
    return counts[:nodes]
