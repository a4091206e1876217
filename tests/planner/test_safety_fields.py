"""The safety models' fields per home at scale (planner/constraints.py, planner/field_rows.py):
fields and models no UAV reads any more are dropped, and whatever is read again after a drop
is what a model that never dropped anything answers, so the decisions do not depend on it
(benchmarks/bench_scale.py --against REV compares whole flights with an older revision)."""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from planner.breadth_first import Scratch, move_counts
from planner.constraints import SafetyModel, SafetyModels
from planner.field_rows import CountRows
from planner.grid import Grid
from planner.scenario import load_scenario

GRID = Grid(100, 100, 1.0)


def _threats() -> tuple[np.ndarray, np.ndarray]:
    scenario = load_scenario("paper-10uav")
    xy = np.array([[t.x_km, t.y_km] for t in scenario.threats])
    return xy, np.array([t.radius_km for t in scenario.threats])


def _make(known: np.ndarray, searched: dict[int, float] | None) -> SafetyModel:
    xy, radii = _threats()
    return SafetyModel(GRID, xy[known], radii[known], 0.0, 45.0, 1.0, searched)


def _answers(model: SafetyModel, homes: np.ndarray, within: int) -> list[np.ndarray]:
    """Everything a UAV at home ``homes[i]`` reads: km, cell moves and (heading, cell) moves
    home from every cell and heading."""
    x, y, h = np.meshgrid(np.arange(GRID.nx), np.arange(GRID.ny), np.arange(8), indexing="ij")
    x, y, h = (np.broadcast_to(a[None], (len(homes), *a.shape)) for a in (x, y, h))
    return [
        model.distances_home_at(homes, x[..., 0], y[..., 0]),
        model._cell_hops(homes, x, y, h),
        model._state_hops(homes, x, y, h, within),
    ]


def test_fields_read_again_after_a_drop_are_the_same_as_never_dropped() -> None:
    known = np.ones(len(_threats()[1]), dtype=bool)
    homes = np.array([GRID.flat(np.array([10, 10])), GRID.flat(np.array([80, 30]))])
    models = SafetyModels(_make)
    kept = _make(known, None)  # never drops anything
    first = _answers(models.get(known, 0), homes, within=80)
    assert all(np.array_equal(a, b) for a, b in zip(first, _answers(kept, homes, 80), strict=True))
    for step in range(1, 4):  # only the first home is read: the second's fields go
        _answers(models.get(known, step), homes[:1], within=80)
        models.drop_unused(step)
    assert homes[1] not in models.get(known, 4)._states
    # asked less far now: a search as far as the dropped one's, as the kept model has it
    again = _answers(models.get(known, 4), homes, within=30)
    expected = _answers(kept, homes, within=30)
    assert all(np.array_equal(a, b) for a, b in zip(again, expected, strict=True))
    far = np.isfinite(again[2][1]) & (again[2][1] > 30 + 20)
    assert far.any()  # counts beyond this call's reach, kept from the first search
    # the whole model dropped (no UAV asked it for two steps), then built again
    models.drop_unused(7)
    assert len(models) == 0
    rebuilt = _answers(models.get(known, 8), homes, within=30)
    assert all(np.array_equal(a, b) for a, b in zip(rebuilt, expected, strict=True))


def test_counts_beyond_sixteen_bits_are_kept_exactly() -> None:
    rows = CountRows((3,), rows=4)
    rows.put(7, np.array([0.0, 12.0, np.inf]))
    assert rows.data.dtype == np.uint8
    rows.put(8, np.array([300.0, 12.0, np.inf]))  # widens the store to 16 bits
    assert rows.data.dtype == np.uint16
    rows.put(9, np.array([70000.0, 1.0, np.inf]))  # and to float32
    got = rows.take((rows.rows(np.array([7, 8, 9])),))
    assert np.array_equal(got, [[0.0, 12.0, np.inf], [300.0, 12.0, np.inf], [70000.0, 1.0, np.inf]])


def test_fields_are_searched_only_as_far_as_the_cells_asked() -> None:
    """A UAV near its home asks its fields near it: they are searched about as far (a search
    of the whole area costs ten times as much on 200 x 200 cells) and answer what the whole
    area's search answers; a cell asked beyond is searched for again, further."""
    known = np.ones(len(_threats()[1]), dtype=bool)
    model, whole = _make(known, None), _make(known, None)
    home = np.array([GRID.flat(np.array([10, 10]))])
    x, y, h = np.array([[12, 13, 14]]), np.array([[9, 10, 11]]), np.array([[0, 1, 2]])
    near = [model.distances_home_at(home, x, y), model._cell_hops(home, x, y, h)]
    assert np.array_equal(near[0], whole.distance_home_km(int(home[0]))[x, y])
    assert np.array_equal(near[1], whole._cell_hops(home, x, y, h))
    for fields in (model._distances, model._hops):
        assert np.isinf(fields.take((0, 90, 90)))  # not searched so far
    far = [model.distances_home_at(home, x + 70, y + 80), model._cell_hops(home, x + 70, y + 80, h)]
    assert np.all(np.isfinite(far[0])) and np.all(np.isfinite(far[1]))
    assert np.array_equal(far[0], whole.distance_home_km(int(home[0]))[x + 70, y + 80])
    assert np.array_equal(far[1], whole._cell_hops(home, x + 70, y + 80, h))


def test_a_threat_far_from_home_leaves_the_fields_near_it_to_be_borrowed() -> None:
    """A UAV that hears of a threat far from its home moves to the model of its new set of
    threats: that model takes the fields near the home from the model the UAV left (the ways
    home there do not come near the new threat) instead of searching them, and answers what a
    model that searched them answers."""
    xy, _ = _threats()
    home_cell = np.array([10, 10])
    farthest = int(np.argmax(np.hypot(*(xy - GRID.centre_km(home_cell)).T)))
    before = np.ones(len(xy), dtype=bool)
    before[farthest] = False
    after = np.ones(len(xy), dtype=bool)
    models = SafetyModels(_make)
    home = np.array([GRID.flat(home_cell)])
    x, y, h = np.array([[12, 13, 14]]), np.array([[9, 10, 11]]), np.array([[0, 1, 2]])

    def _near(model: SafetyModel) -> list[np.ndarray]:
        return [model.distances_home_at(home, x, y), model._cell_hops(home, x, y, h),
                model._state_hops(home, x, y, h, 30)]  # fmt: skip

    _near(models.get(before, 0))
    borrower = models.get(after, 1)
    got = _near(borrower)
    expected = _near(_make(after, None))
    assert all(np.array_equal(a, b) for a, b in zip(got, expected, strict=True))
    searched = {"_reversed_graph", "_reversed_hop_graph", "_state_neighbours"}
    assert not searched & set(vars(borrower))  # no graph of its own built: nothing searched


def test_breadth_first_counts_are_the_dijkstra_counts_over_the_same_moves() -> None:
    """The turn-limited way home is counted level by level (planner/breadth_first.py): the
    counts are scipy's Dijkstra's over the same (heading, cell) moves as a sparse graph of
    ones, to the bit, however far the search is limited, from any home (the area's corner, a
    threat's edge, the open), one search after another in the same work arrays."""
    model = _make(np.ones(len(_threats()[1]), dtype=bool), None)
    table = model._state_neighbours
    rows = np.repeat(np.arange(len(table)), table.shape[1])
    cols = table.ravel()
    real = cols < len(table)  # the padding is no move
    graph = csr_matrix((np.ones(real.sum()), (rows[real], cols[real])), shape=(len(table),) * 2)
    xy, radii = _threats()
    edge = GRID.cell_of(xy[0] + np.array([radii[0] + 0.5, 0.0]))
    scratch = Scratch()  # one for every search, as the models of a swarm share one
    for cell in (np.array([0, 0]), np.array([50, 50]), edge, np.array([99, 3])):
        states = 8 * GRID.flat(cell) + np.arange(8)
        for limit in (0, 1, 7, 23.0, 60, np.inf):
            expected = dijkstra(graph, indices=states, min_only=True, limit=limit)
            got = move_counts(table, states, limit, scratch)
            assert got.dtype == expected.dtype and np.array_equal(got, expected)
            assert np.isfinite(got).sum() > (limit > 0)  # the search went somewhere


def test_a_count_field_cut_in_its_store_is_the_float_field_cut() -> None:
    """A field lent to another model is cut where it stops being exact in the store's own type
    (planner/field_rows.py ``CountRows.cut``): the same counts, and inf as the store writes
    it, as cutting the float64 counts and storing them, for every width of the store."""
    rng = np.random.default_rng(0)
    for width in (np.uint8, np.uint16, np.float32):
        store = CountRows((8, 20, 30), 2)
        counts = rng.integers(0, 300, (8, 20, 30)).astype(float)
        counts[counts > 250] = np.inf
        if width is np.uint8:
            counts = np.minimum(counts, 250)
        while store.data.dtype != width:
            store._widen()
        store.put(7, counts, 100.0 if width is np.uint8 else np.inf)
        row = store.row_of(7)
        for exact in (-0.5, 0.0, 0.999999, 37.999999, 38.0, 254.5, 255.0, 65535.0, 7e4, np.inf):
            cut = np.where(store.take(row) <= exact, store.take(row), np.inf)
            store.put(8, cut)  # the float64 way: cut, then stored
            got = store.cut(row, exact)
            assert got.dtype == store.data.dtype
            assert np.array_equal(got, store.data[store.row_of(8)]), (width, exact)
