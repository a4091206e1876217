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


class Scratch:
    """Work arrays of ``move_counts``, kept between searches over tables of one size (the
    safety models of a swarm share one): a fresh array of counts for every search faulted in
    its pages each time; between searches only the nodes reached are set back."""

    def __init__(self) -> None:
        self.counts = np.empty(0)  # per node and the padding: its count, inf unreached
        self.order = np.empty(0, dtype=np.int64)
        self.reached: list[np.ndarray] = []  # the nodes the last search reached

    def ready(self, nodes: int) -> np.ndarray:
        """The counts for a search over ``nodes`` nodes, every one unreached."""
        if len(self.counts) != nodes + 1:
            self.counts = np.full(nodes + 1, np.inf)
            self.counts[nodes] = -1.0  # the padding: never reached
            self.order = np.empty(nodes + 1, dtype=np.int64)
        else:
            for reached in self.reached:
                self.counts[reached] = np.inf
        self.reached = []
        return self.counts


def move_counts(
    neighbours: np.ndarray, sources: np.ndarray, limit: float, scratch: Scratch | None = None
) -> np.ndarray:
    """(nodes,) float64: the fewest moves from any of ``sources`` to each node over
    ``neighbours`` (a ``neighbour_table``), counted as far as ``limit`` moves (inf beyond, and
    where no way is): what ``scipy.sparse.csgraph.dijkstra(graph, indices=sources,
    min_only=True, limit=limit)`` gives for the graph of the table with every move one. With
    ``scratch``, the counts are its array, good until its next search."""
    nodes = len(neighbours)
    scratch = scratch or Scratch()
    counts = scratch.ready(nodes)
    order = scratch.order  # to keep one of each node reached
    frontier = np.unique(np.asarray(sources, dtype=np.int64))
    counts[frontier] = 0.0
    scratch.reached.append(frontier)
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
        scratch.reached.append(frontier)
    return counts[:nodes]
