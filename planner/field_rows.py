"""Per-home fields of one safety model (``planner.constraints.SafetyModel``) in one array, so
that a batch of UAVs reads its fields in one gather.

The array grows by doubling its rows: a field added is one copy of the rows kept so far only
when the array is full (numpy's fresh rows take memory only once written), where growing it by
one row a field copied every field each time (100 UAVs on 200 x 200 cells spent a third of
their planning time there). A row no UAV has read for a step (its UAV has learnt another
threat, and with it gone to another model) is freed for the next field (``drop_unread``).
"""

from __future__ import annotations

import numpy as np


class FieldRows:
    """Fields of one shape and type, one row per home cell (flat index)."""

    def __init__(self, shape: tuple[int, ...], dtype: type) -> None:
        self.data = np.empty((0, *shape), dtype=dtype)
        self._rows: dict[int, int] = {}  # home cell -> row of ``data``
        self._index: dict[bytes, np.ndarray] = {}  # a homes array's bytes -> its rows
        self._free: list[int] = []  # rows of dropped fields
        self._read = np.zeros(0, dtype=np.int64)  # per row: the last step it was read at

    def __contains__(self, home: int) -> bool:
        return home in self._rows

    def put(self, home: int, field: np.ndarray) -> None:
        """Store (or replace) the field of ``home``."""
        row = self._rows.get(home)
        if row is None:
            row = self._free.pop() if self._free else len(self._rows)
            if row == len(self.data):
                grown = np.empty((max(4, 2 * row), *self.data.shape[1:]), self.data.dtype)
                grown[:row] = self.data
                self.data = grown
                self._read = np.concatenate([self._read, np.zeros(len(grown) - row, np.int64)])
            self._rows[home] = row
        self.data[row] = field

    def rows(self, homes: np.ndarray, step: int = 0) -> np.ndarray:
        """The rows of ``homes`` (every one stored), read at decision step ``step``; the same
        UAVs ask every step, so the rows of a homes array are kept."""
        homes = np.asarray(homes, dtype=np.int64)
        key = homes.tobytes()
        rows = self._index.get(key)
        if rows is None:
            rows = self._index[key] = np.array([self._rows[h] for h in homes.tolist()], np.int64)
        self._read[rows] = step
        return rows

    def drop_unread(self, step: int) -> None:
        """Free the fields not read at ``step`` nor the step before."""
        stale = [h for h, row in self._rows.items() if self._read[row] < step - 1]
        if stale:
            self._free.extend(self._rows.pop(h) for h in stale)
            self._index.clear()


class CountRows(FieldRows):
    """Fields of move counts (whole numbers, inf where no way is) as uint16, ``NONE`` for inf:
    exact, in a quarter of float64's memory; widened to float32 (exact as well) should a count
    ever reach ``NONE``."""

    NONE = np.iinfo(np.uint16).max

    def __init__(self, shape: tuple[int, ...]) -> None:
        super().__init__(shape, np.uint16)

    def put(self, home: int, field: np.ndarray) -> None:
        finite = np.isfinite(field)
        if self.data.dtype == np.uint16:
            if np.max(field, where=finite, initial=0) >= self.NONE:
                self.data = self.take(slice(None)).astype(np.float32)
            else:
                field = np.where(finite, field, self.NONE)
        super().put(home, field)

    def take(self, index: tuple | slice) -> np.ndarray:
        """``data[index]`` as float64 counts, inf where no way is."""
        counts = self.data[index]
        if counts.dtype == np.uint16:
            return np.where(counts == self.NONE, np.inf, counts)
        return counts.astype(float)
