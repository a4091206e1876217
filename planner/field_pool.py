"""The fields of the way home of every safety model of a swarm in one store per kind
(``planner.constraints.SafetyModels``): a row freed by one model (its UAVs have learnt another
threat and moved on) is written again by the next, where a store per model kept every row its
UAVs ever used. 100 UAVs on 200 x 200 cells in 40 steps went through about 500 (model, home)
pairs of which about 150 are read at any one time.
"""

from __future__ import annotations

import numpy as np

from planner.breadth_first import Scratch
from planner.field_rows import CountRows, FieldRows


class FieldPool:
    """The km, the cell moves and the (heading, cell) moves home, one store each, for the
    fields of the homes of one or more models (``FieldsView``), on a grid of ``shape``."""

    def __init__(self, shape: tuple[int, int], homes: int) -> None:
        """Room for the fields of ``homes`` homes twice over from the start (rows take memory
        only once written)."""
        self.distances = FieldRows(shape, np.float64, 2 * homes)
        self.hops = CountRows(shape, 2 * homes)
        self.states = CountRows((8, *shape), 2 * homes)
        self.scratch = Scratch()  # the (heading, cell) searches' work arrays

    def drop_unread(self, step: int) -> None:
        """Free the fields not read at ``step`` nor the step before (``FieldRows``)."""
        for store in (self.distances, self.hops, self.states):
            store.drop_unread(step)


class FieldsView:
    """One model's fields of one kind, by home cell, in a store shared with other models: the
    store's key of a home is ``offset`` + the home's flat index (the model's own offset)."""

    def __init__(self, store: FieldRows, offset: int) -> None:
        self.store = store
        self.offset = offset

    @property
    def data(self) -> np.ndarray:
        return self.store.data

    @property
    def reach(self) -> np.ndarray:
        return self.store.reach

    def __contains__(self, home: int) -> bool:
        return self.offset + home in self.store

    def put(self, home: int, field: np.ndarray, reach: float = np.inf) -> None:
        self.store.put(self.offset + home, field, reach)

    def put_stored(self, home: int, field: np.ndarray, reach: float) -> None:
        self.store.put_stored(self.offset + home, field, reach)

    def cut(self, row: int, exact: float) -> np.ndarray:
        return self.store.cut(row, exact)

    def rows(self, homes: np.ndarray, step: int = 0) -> np.ndarray:
        return self.store.rows(np.asarray(homes, dtype=np.int64) + self.offset, step)

    def row_of(self, home: int) -> int:
        return self.store.row_of(self.offset + home)

    def take(self, index: tuple | slice | np.ndarray) -> np.ndarray:
        return self.store.take(index)
