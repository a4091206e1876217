"""Per-home fields of one safety model (``planner.constraints.SafetyModel``) in one array, so
that a batch of UAVs reads its fields in one gather.

The array grows by doubling its rows: a field added is one copy of the rows kept so far only
when the array is full (numpy's fresh rows take memory only once written), where growing it by
one row a field copied every field each time (100 UAVs on 200 x 200 cells spent a third of
their planning time there). A row no UAV has read for a step (its UAV has learnt another
threat, and with it gone to another model) is freed for the next field (``drop_unread``).

A field need not be searched over the whole area: a search that stops at a distance ``reach``
from the home (scipy's Dijkstra ``limit``) gives every cell nearer than that its exact value and
the others inf (a shortest path's cells are all nearer than its end), so ``rows_reaching``
searches each home only as far as the cells its UAVs ask about, and further once they ask
beyond (the UAVs of 40-step runs stay within some 20-40 cells of home: a field on 200 x 200
cells then costs a tenth of the whole area's search).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: a home's first search reaches this many times the farthest asked cell's distance with no
#: threats, plus ``FIRST_REACH_CELLS`` cells (threats make ways home longer); a search found
#: short is made again twice as far
FIRST_REACH_FACTOR = 1.5
FIRST_REACH_CELLS = 5


class FieldRows:
    """Fields of one shape and type, one row per home cell (flat index)."""

    def __init__(self, shape: tuple[int, ...], dtype: type, rows: int = 0) -> None:
        """Room for ``rows`` fields from the start (the homes of a swarm: a row takes memory
        only once written, and growing the array copies every field kept)."""
        self.data = np.empty((rows, *shape), dtype=dtype)
        self._rows: dict[int, int] = {}  # home cell -> row of ``data``
        self._index: dict[bytes, np.ndarray] = {}  # a homes array's bytes -> its rows
        self._free: list[int] = []  # rows of dropped fields
        self._read = np.zeros(rows, dtype=np.int64)  # per row: the last step it was read at
        #: per row: how far from its home the field was searched (inf: all of it)
        self.reach = np.zeros(rows)

    def __contains__(self, home: int) -> bool:
        return home in self._rows

    def put(self, home: int, field: np.ndarray, reach: float = np.inf) -> None:
        """Store (or replace) the field of ``home``, searched as far as ``reach``."""
        row = self._row_for(home)
        self.data[row] = field
        self.reach[row] = reach

    def _row_for(self, home: int) -> int:
        """The row of ``home``'s field: its own, else a free one (the store grown if none
        is)."""
        row = self._rows.get(home)
        if row is None:
            row = self._free.pop() if self._free else len(self._rows)
            if row == len(self.data):
                grown = np.empty((max(4, 2 * row), *self.data.shape[1:]), self.data.dtype)
                grown[:row] = self.data
                self.data = grown
                self._read = np.concatenate([self._read, np.zeros(len(grown) - row, np.int64)])
                self.reach = np.concatenate([self.reach, np.zeros(len(grown) - row)])
            self._rows[home] = row
        return row

    def put_stored(self, home: int, field: np.ndarray, reach: float) -> None:
        """``put`` a field already in this store's form (``cut``: its type, its value for
        inf), as it is."""
        if field.dtype != self.data.dtype:
            raise ValueError(f"a field of {field.dtype} put as stored in {self.data.dtype}")
        FieldRows.put(self, home, field, reach)

    def cut(self, row: int, exact: float) -> np.ndarray:
        """The field of ``row`` in this store's form, inf (as stored) where it is more than
        ``exact``: a field lent to another home's model (``planner.shared_fields``) without
        a round trip through float64."""
        field = self.data[row]
        # compared in float64 (a float32 store's values against the float ``exact``)
        return np.where(field <= np.float64(exact), field, self.data.dtype.type(self.none))

    @property
    def none(self) -> float:
        """The stored value that stands for inf."""
        return np.inf

    def take(self, index: tuple | slice) -> np.ndarray:
        """``data[index]``, inf where no way is (or none was searched)."""
        return self.data[index]

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

    def row_of(self, home: int) -> int:
        """The row of ``home`` (stored), not counted as read."""
        return self._rows[home]

    def drop_unread(self, step: int) -> None:
        """Free the fields not read at ``step`` nor the step before."""
        stale = [h for h, row in self._rows.items() if self._read[row] < step - 1]
        if stale:
            self._free.extend(self._rows.pop(h) for h in stale)
            self._index.clear()


class CountRows(FieldRows):
    """Fields of move counts (whole numbers, inf where no way is) in the narrowest of uint8,
    uint16 and float32 that holds every count, the unsigned types' largest value standing for
    inf: exact, in an eighth (a quarter) of float64's memory. A field searched less far than
    255 moves (the 40-step runs of 100 UAVs on 200 x 200 cells) fits in uint8, which halves
    what the turn-limited searches' fields keep; the first count too large widens the store."""

    WIDER = {np.dtype(np.uint8): np.uint16, np.dtype(np.uint16): np.float32}

    def __init__(self, shape: tuple[int, ...], rows: int = 0) -> None:
        super().__init__(shape, np.uint8, rows)

    @property
    def none(self) -> float:
        dtype = self.data.dtype
        return float(np.iinfo(dtype).max) if dtype.kind == "u" else np.inf

    def cut(self, row: int, exact: float) -> np.ndarray:
        field = self.data[row]
        dtype = field.dtype
        if dtype.kind != "u":
            return super().cut(row, exact)
        if exact >= self.none:
            return field.copy()
        if exact < 0:
            return np.full_like(field, self.none)
        # whole numbers: at most ``exact`` is at most its floor, compared in the store's type;
        # the others OR'd with all ones, the largest value: none (a tenth of ``np.where``'s time)
        over = (field > dtype.type(np.floor(exact))).astype(dtype)
        return field | np.negative(over, out=over)

    def put(self, home: int, field: np.ndarray, reach: float = np.inf) -> None:
        while self.data.dtype.kind == "u":
            # a field searched less far than ``none`` holds no count as large
            if reach < self.none or np.max(field, where=np.isfinite(field), initial=0) < self.none:
                row = self._row_for(home)
                # inf -> none, written into the row in one pass (whole numbers: cast exactly)
                np.minimum(field, self.none, out=self.data[row], casting="unsafe")
                self.reach[row] = reach
                return
            self._widen()
        super().put(home, field, reach)

    def _widen(self) -> None:
        """The next wider store, the fields kept copied (the rows never written are not
        touched: they take no memory)."""
        wider = self.WIDER[self.data.dtype]
        used = np.fromiter(self._rows.values(), dtype=np.int64, count=len(self._rows))
        counts = self.take(used)
        self.data = np.empty(self.data.shape, dtype=wider)
        self.data[used] = np.minimum(counts, self.none)  # inf -> the wider none

    def take(self, index: tuple | slice | np.ndarray) -> np.ndarray:
        """``data[index]`` as float64 counts, inf where no way is."""
        counts = self.data[index]
        if counts.dtype.kind == "u":
            return np.where(counts == np.iinfo(counts.dtype).max, np.inf, counts)
        return counts.astype(float)


def free_distance(
    home: int, x: np.ndarray, y: np.ndarray, ny: int, move_lengths: tuple[float, float]
) -> np.ndarray:
    """The length of the fewest moves from each cell (x, y) to ``home`` (a flat cell) with no
    threats in the way (no way is shorter), straight and diagonal moves of ``move_lengths``."""
    straight, diagonal = move_lengths
    dx, dy = np.abs(x - home // ny), np.abs(y - home % ny)
    near, far = np.minimum(dx, dy), np.maximum(dx, dy)
    return straight * (far - near) + diagonal * near


#: ``borrow(home, (wanted, most))``: a field of ``home`` exact as far as ``wanted`` or more
#: (inf beyond ``most``), from elsewhere, in the store's form (``FieldRows.cut``), and how far
#: it is exact; or None
Borrow = Callable[[int, tuple[float, float]], "tuple[np.ndarray, float] | None"]


def rows_reaching(
    fields: FieldRows,
    homes: np.ndarray,
    cells: tuple[np.ndarray, ...],
    search: Callable[[int, float], np.ndarray],
    move_lengths: tuple[float, float],
    dead_end: np.ndarray,
    step: int,
    bound: Callable[[int], float] = lambda home: np.inf,
    borrow: Borrow | None = None,
) -> np.ndarray:
    """The rows of ``fields`` for ``homes`` (M,) read at ``step``, each home's field searched far
    enough that its values at the cells ``cells`` (index arrays (M, ...) into a field, the last
    two x and y) asked for it are exact as far as ``bound(home)``, and inf beyond.

    ``search(home, reach)`` makes the field of ``home`` (a flat cell) as far as ``reach`` (inf
    beyond); ``move_lengths`` are a straight and a diagonal move's lengths in the field's unit
    (``free_distance``); ``dead_end`` (a field's shape, bool) marks where no move leads on, inf
    in a field searched however far. A missing field is borrowed (``borrow``,
    ``planner.shared_fields``) when it can be, else searched as far again as the farthest cell
    asked by ``free_distance``, and a little. A value still inf in a field searched short of
    ``bound`` is searched for again twice as far (as far as ``bound``, or over the whole area
    once twice as far passes ``2 (nx + ny)`` straight moves)."""
    x, y = cells[-2:]
    homes = np.asarray(homes, dtype=np.int64)
    ny = dead_end.shape[-1]
    whole = 2.0 * move_lengths[0] * sum(dead_end.shape[-2:])
    for home in dict.fromkeys(homes.tolist()):
        if home not in fields:
            asked = homes == home
            free = float(free_distance(home, x[asked], y[asked], ny, move_lengths).max())
            reach = FIRST_REACH_FACTOR * free + FIRST_REACH_CELLS * move_lengths[0]
            reach = min(reach, bound(home))
            lent = None if borrow is None else borrow(home, (reach, bound(home)))
            if lent is None:
                fields.put(home, search(home, reach), reach)
            else:
                fields.put_stored(home, *lent)
    while True:
        rows = fields.rows(homes, step)
        short = fields.reach[rows] < np.array([bound(home) for home in homes.tolist()])
        if not short.any():  # every field searched as far as it can be asked
            return rows
        shaped = rows.reshape((-1,) + (1,) * (np.ndim(x) - 1))
        unknown = ~np.isfinite(fields.take((shaped, *cells))) & ~dead_end[cells]
        short &= unknown.reshape(len(homes), -1).any(axis=1)
        if not short.any():
            return rows
        short_rows = dict(zip(homes[short].tolist(), rows[short].tolist(), strict=True))
        for home, row in short_rows.items():
            reach = 2.0 * fields.reach[row]
            reach = min(np.inf if reach > whole else reach, bound(home))
            fields.put(home, search(home, reach), reach)
