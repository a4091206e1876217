"""The constraints of eq 5, as the planner enforces them and as the metrics count them.

- C_m (turn): only the candidate cells of ``planner.grid.candidate_moves`` are ever offered.
- C_t (threats): a move is allowed only if its straight segment stays outside every known threat
  circle (plus ``threat_margin_km``) and ends in a *viable* state: one from which some
  turn-limited path stays safe for ever (a viability kernel over (heading, cell) computed by
  fixed-point iteration, so a UAV never flies into a pocket it cannot turn out of). The area's
  edge is treated the same way.
- C_r (range): a move is allowed only if, after it, the distance flown plus the shortest
  threat-avoiding path home (Dijkstra on the 8-connected grid, scipy.sparse.csgraph) plus a
  reserve for turns stays within L_max.
- C_c (separation) is resolved in ``planner.transition`` where the UAVs claim their next cells.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from functools import cached_property
from weakref import WeakKeyDictionary

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from planner.breadth_first import move_counts, neighbour_table
from planner.field_pool import FieldPool, FieldsView
from planner.field_rows import Borrow, rows_reaching
from planner.grid import HEADING_LENGTHS, HEADING_STEPS, Grid, turn_options
from planner.shared_fields import borrowed_field, changed_cells


def segment_clearance(
    p0: np.ndarray, p1: np.ndarray, centres: np.ndarray, radii: np.ndarray
) -> np.ndarray:
    """Smallest (distance to centre - radius) over threats along segments p0->p1 (..., 2) km;
    +inf when there are no threats. Negative means the segment enters a threat."""
    if len(radii) == 0:
        return np.full(np.shape(p0)[:-1], np.inf)
    a = np.asarray(p0, float)[..., None, :]
    b = np.asarray(p1, float)[..., None, :]
    ab = b - a
    ap = centres - a
    denom = np.maximum(np.sum(ab * ab, axis=-1), 1e-12)
    t = np.clip(np.sum(ap * ab, axis=-1) / denom, 0.0, 1.0)
    closest = a + t[..., None] * ab
    gap = closest - centres
    d = np.hypot(gap[..., 0], gap[..., 1])
    return np.min(d - radii, axis=-1)


#: how many steps a turn-limited way home may be longer than its count in cell moves (plus the
#: turns onto the first) before ``SafetyModel.hops_home_at`` must search the (heading, cell)
#: states: twice the most measured (10, see there)
HOP_SEARCH_SLACK = 20


class SafetyModel:
    """Move safety and viability for one set of known threats (cached by the planner)."""

    def __init__(self, grid: Grid, threat_xy: np.ndarray, threat_r: np.ndarray, margin_km: float,
                 max_turn_deg: float, home_margin_km: float | None = None,
                 searched: dict[int, float] | None = None, homes: int = 4) -> None:  # fmt: skip
        """``homes``: how many homes the model may be asked for (room for their fields)."""
        self.grid = grid
        self.threat_xy = threat_xy.reshape(-1, 2)
        self.threat_r = threat_r + margin_km
        self.turns = turn_options(max_turn_deg)
        #: edge_safe[h, x, y]: the move from (x, y) along heading h is inside and clear of threats.
        self.edge_safe = self._safe_moves(self.threat_r)
        #: the moves the way home is counted over (``hops_home_at``, ``distance_home_km``): clear
        #: of the threats by ``home_margin_km`` (a flown plane keeps a wider berth than the grid)
        self.home_edge_safe = self.edge_safe
        if home_margin_km is not None and home_margin_km > margin_km and len(threat_r):
            wide = threat_r + home_margin_km
            in_band = self._centre_gap_km(wide) <= 0  # from there, by the grid's own moves
            self.home_edge_safe = self._safe_moves(wide) | (self.edge_safe & in_band[None])
        self.viable = self._viability_kernel()
        self.use_pool(FieldPool((grid.nx, grid.ny), homes), 0)
        #: home cell -> how far its state search went (``searched``: the searches of an earlier
        #: model of the same threats, dropped by ``SafetyModels``, to be made as far again)
        self.state_limits: dict[int, float] = dict(searched or {})
        self.step = 0  # the decision step the model is asked at (``SafetyModels``)
        #: the models of the swarm, to borrow fields from (set by ``SafetyModels``)
        self.lenders: Callable[[], Iterable[SafetyModel]] = tuple
        #: per kind of field, per other model: the cells where the moves differ
        self._changed: dict[str, WeakKeyDictionary[SafetyModel, np.ndarray]] = {}

    def use_pool(self, pool: FieldPool, serial: int) -> None:
        """Keep the fields per home in ``pool``'s stores, as the model numbered ``serial`` of
        those sharing it (``SafetyModels``); before any field is made."""
        self.pool = pool
        offset = serial * self.grid.size
        self._distances = FieldsView(pool.distances, offset)  # per home: ``distance_home_km``
        self._hops = FieldsView(pool.hops, offset)  # per home: the fewest cell moves home
        self._states = FieldsView(pool.states, offset)  # per home: ``_state_hops``'s search

    def drop_unread(self, step: int) -> None:
        """Free the fields per home not read at ``step`` nor the step before: read again, they
        are made again, the same (a state search as far as it went: ``state_limits`` keeps it).
        """
        self.pool.drop_unread(step)

    def _cells(self) -> np.ndarray:
        """(nx, ny, 2): every cell's index."""
        ix, iy = np.meshgrid(np.arange(self.grid.nx), np.arange(self.grid.ny), indexing="ij")
        return np.stack([ix, iy], axis=-1)

    def _centre_gap_km(self, radii: np.ndarray) -> np.ndarray:
        """(nx, ny): distance (km) from each cell's centre to the nearest threat circle of
        ``radii`` (negative inside one, inf without threats)."""
        if not len(radii):
            return np.full(self.grid.shape, np.inf)
        centres = self.grid.centre_km(self._cells())
        gap = np.hypot(*(centres[..., None, :] - self.threat_xy).transpose(3, 0, 1, 2)) - radii
        return gap.min(axis=-1)

    def _safe_moves(self, radii: np.ndarray) -> np.ndarray:
        """safe[h, x, y]: the move from (x, y) along heading h ends inside the area and its leg
        keeps clear of every threat circle of ``radii``."""
        grid = self.grid
        cells = self._cells()
        start = grid.centre_km(cells)
        # only moves starting within one diagonal step of a threat circle can touch it
        near = self._centre_gap_km(radii) <= np.sqrt(2) * grid.cell_km + 1e-9
        safe = np.zeros((8, grid.nx, grid.ny), dtype=bool)
        for h in range(8):
            nxt = cells + HEADING_STEPS[h]
            clear = np.ones(grid.shape, dtype=bool)
            clear[near] = (
                segment_clearance(start[near], grid.centre_km(nxt[near]), self.threat_xy, radii) > 0
            )
            safe[h] = grid.inside(nxt) & clear
        return safe

    def _shifted(self, viable_h: np.ndarray, h: int, outside: float = False) -> np.ndarray:
        """value[..., x, y] = viable_h[..., (x, y) + step(h)] (``outside`` beyond the area's
        edge); leading axes are kept."""
        dx, dy = HEADING_STEPS[h]
        out = np.full_like(viable_h, outside)
        nx, ny = viable_h.shape[-2:]
        xs = slice(max(0, -dx), nx - max(0, dx))
        ys = slice(max(0, -dy), ny - max(0, dy))
        xd = slice(max(0, dx), nx - max(0, -dx))
        yd = slice(max(0, dy), ny - max(0, -dy))
        out[..., xs, ys] = viable_h[..., xd, yd]
        return out

    def _viability_kernel(self) -> np.ndarray:
        """viable[h, x, y]: having arrived at (x, y) with heading h, some turn-limited path of
        safe moves goes on for ever. Greatest fixed point of V = OR_turns(safe & V(next))."""
        viable = np.ones((8, self.grid.nx, self.grid.ny), dtype=bool)
        for _ in range(4 * (self.grid.nx + self.grid.ny)):
            can_go = np.stack([self.edge_safe[h] & self._shifted(viable[h], h) for h in range(8)])
            new = np.zeros_like(viable)
            for h in range(8):
                for t in self.turns:
                    new[h] |= can_go[(h + t) % 8]
            if np.array_equal(new, viable):
                break
            viable = new
        return viable

    def move_allowed(self, cells: np.ndarray, headings: np.ndarray) -> np.ndarray:
        """C_t and the area: the move from ``cells`` along ``headings`` (next heading) is safe and
        lands in a viable state. Shapes (..., 2) and (...)."""
        grid = self.grid
        nxt = cells + HEADING_STEPS[headings]
        return (
            grid.inside(cells)
            & self.edge_safe.reshape(8, -1)[headings, grid.clipped_flat(cells)]
            & grid.inside(nxt)
            & self.viable.reshape(8, -1)[headings, grid.clipped_flat(nxt)]
        )

    @cached_property
    def freedom(self) -> np.ndarray:
        """freedom[h, x, y]: how many allowed moves (``move_allowed``) a UAV that arrived at
        (x, y) with heading h has next. 1 means a single way on: two UAVs in such states near
        each other (a corner of the area, a gap between threats) can be left no separated pair
        of moves, so the separation claim avoids entering them when others are close."""
        grid = self.grid
        # move_allowed over the whole area: a safe move that lands in a viable state
        can_go = [self.edge_safe[h] & self._shifted(self.viable[h], h) for h in range(8)]
        count = np.zeros((8, grid.nx, grid.ny), dtype=np.int8)  # at most 8
        for h in range(8):
            for t in self.turns:
                count[h] += can_go[(h + t) % 8]
        return count

    @cached_property
    def _reversed_graph(self) -> csr_matrix:
        """The safe moves as a sparse graph with reversed edges (distances *to* a cell)."""
        grid = self.grid
        rows, cols, weights = [], [], []
        flat = np.arange(grid.size).reshape(grid.shape)
        for h in range(8):
            start = flat[self.home_edge_safe[h]]  # safe moves end inside: one flat step further
            cols.append(start)
            rows.append(start + grid.flat(HEADING_STEPS[h]))
            weights.append(np.full(len(start), HEADING_LENGTHS[h] * grid.cell_km))
        return csr_matrix(
            (np.concatenate(weights), (np.concatenate(rows), np.concatenate(cols))),
            shape=(grid.size, grid.size),
        )

    @cached_property
    def _reversed_hop_graph(self) -> csr_matrix:
        """``_reversed_graph`` with every move one (cell moves *to* a cell): scipy's
        ``unweighted`` search, without making the ones again at every search."""
        graph = self._reversed_graph.copy()
        graph.data[:] = 1.0
        return graph

    @cached_property
    def _dead_ends(self) -> np.ndarray:
        """(nx, ny): the cells no move of ``home_edge_safe`` leaves (no way home, however far
        a field is searched)."""
        return ~self.home_edge_safe.any(axis=0)

    @property
    def _km_lengths(self) -> tuple[float, float]:
        """A straight and a diagonal move's lengths (km)."""
        return (self.grid.cell_km * HEADING_LENGTHS[0], self.grid.cell_km * HEADING_LENGTHS[1])

    def _borrow(self, kind: str) -> Borrow:
        """``borrow`` of ``rows_reaching`` for the fields ``kind`` (the attribute's name):
        from the other models of the swarm (``planner.shared_fields``)."""
        moves = self._state_moves if kind == "_states" else self.home_edge_safe
        changed = self._changed.setdefault(kind, WeakKeyDictionary())

        def changed_from(other: SafetyModel) -> Callable[[], np.ndarray]:
            def cells() -> np.ndarray:
                if other not in changed:
                    theirs = other._state_moves if kind == "_states" else other.home_edge_safe
                    changed[other] = changed_cells(moves, theirs)
                return changed[other]

            return cells

        lengths = self._km_lengths if kind == "_distances" else (1.0, 1.0)
        return lambda home, reach: borrowed_field(
            ((getattr(m, kind), changed_from(m)) for m in self.lenders() if m is not self),
            home, reach, self.grid.ny, lengths,
        )  # fmt: skip

    def _search(self, graph: str) -> Callable[[int, float], np.ndarray]:
        """``search(home, reach)``: the shortest ways over the graph named ``graph`` (made at
        the first search) from every cell to ``home``, as far as ``reach`` (inf beyond)."""
        return lambda home, reach: dijkstra(
            getattr(self, graph), indices=home, limit=reach
        ).reshape(self.grid.shape)

    def distance_home_km(self, home_flat: int) -> np.ndarray:
        """Shortest threat-avoiding path length (km) from every cell to ``home_flat``, (nx, ny);
        computed once per home and model (Dijkstra from the home on the reversed graph)."""
        fields = self._distances
        if home_flat not in fields or np.isfinite(fields.reach[fields.rows([home_flat])[0]]):
            fields.put(home_flat, self._search("_reversed_graph")(home_flat, np.inf))
        return fields.data[fields.rows(np.array([home_flat]), self.step)[0]]

    def distances_home_at(self, homes_flat: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """``distance_home_km(homes_flat[i])[x[i], y[i]]`` for arrays of UAVs (homes (M,), cells
        (M, ...)), in one gather."""
        rows = self._distance_rows(np.asarray(homes_flat), x, y)
        return self._distances.data[rows.reshape((-1,) + (1,) * (np.ndim(x) - 1)), x, y]

    def _distance_rows(self, homes: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The rows of the km fields of ``homes``, exact at the cells (x, y) asked."""
        return rows_reaching(
            self._distances, homes, (x, y), self._search("_reversed_graph"), self._km_lengths,
            self._dead_ends, self.step, borrow=self._borrow("_distances"),
        )  # fmt: skip

    def hops_home_at(
        self,
        homes_flat: np.ndarray,
        x: np.ndarray,
        y: np.ndarray,
        headings: np.ndarray,
        within: int | None = None,
    ) -> np.ndarray:
        """Decision steps a UAV at cell ``(x[i], y[i])`` flying heading ``headings[i]`` needs to
        reach ``homes_flat[i]``: the fewest turn-limited safe moves (phi_max a step, over
        ``home_edge_safe``, each into a viable state as ``move_allowed`` asks; a diagonal one
        step) from that cell and heading to the home cell, arriving with any heading (inf where
        none does): a breadth-first search over the (heading, cell) states, once per home and
        model. Counting cell moves and the turns onto the first of them (``_cell_hops``) left
        the turns further on uncounted: beside a threat the way home took more steps than were
        kept (tests/planner/homing.toml).

        With ``within`` (the steps the caller has: only whether a count is within it matters),
        that search, 8 times the cells, is left out for a UAV (row of ``homes_flat``) whose
        fewest count by cell moves is more than ``HOP_SEARCH_SLACK`` from ``within``, either
        way: the cell count is then returned, as no turn-limited way differs from it that much
        (longer by 10 at most, shorter by 3, over the paper's threats with homes every 6 cells;
        ``tests/planner/test_swarm_pieces.py``). The search is made once the UAV's time gets
        near, bounded by ``within`` + ``HOP_SEARCH_SLACK``: a state further is counted inf,
        which a later, smaller ``within`` cannot change."""
        homes = np.asarray(homes_flat)
        if within is None:
            return self._state_hops(homes, x, y, headings, None)
        cell_hops = self._cell_hops(homes, x, y, headings)
        rows = cell_hops.reshape(len(homes), -1)
        near = np.abs(within - rows.min(axis=1)) <= HOP_SEARCH_SLACK
        if not near.any():
            return cell_hops
        out = np.array(cell_hops, copy=True)
        out[near] = self._state_hops(homes[near], x[near], y[near], headings[near], within)
        return out

    def _state_hops(
        self, homes: np.ndarray, x: np.ndarray, y: np.ndarray, headings: np.ndarray,
        within: int | None,
    ) -> np.ndarray:  # fmt: skip
        """The breadth-first count over (heading, cell) states (``hops_home_at``), up to
        ``within`` + ``HOP_SEARCH_SLACK`` (all of it with None); a field is kept per home and
        model, and searched again only when asked further than it was."""
        limit = np.inf if within is None else float(within + HOP_SEARCH_SLACK)
        limits = self.state_limits
        for home in dict.fromkeys(homes.tolist()):
            # as far as asked, and never less far than this home was searched before
            limits[home] = max(limit, limits.get(home, -np.inf))
        size = self.grid.size

        def search(home: int, reach: float) -> np.ndarray:
            states = 8 * home + np.arange(8)  # the home cell, any heading
            # the pool's work array, good until the next search: the caller stores it first
            field = move_counts(self._state_neighbours, states, reach, self.pool.scratch)
            return field.reshape(size, 8).T.reshape(8, *self.grid.shape)

        rows = rows_reaching(
            self._states, homes, (headings, x, y), search, (1.0, 1.0), self._dead_end_states,
            self.step, limits.__getitem__, self._borrow("_states"),
        ).reshape((-1,) + (1,) * (np.ndim(x) - 1))  # fmt: skip
        return self._states.take((rows, headings, x, y))

    def _cell_hops(
        self, homes_flat: np.ndarray, x: np.ndarray, y: np.ndarray, headings: np.ndarray
    ) -> np.ndarray:
        """The fewest safe cell moves home (a diagonal one step) plus the turns beyond the first
        that the heading needs to point along the first move of such a path (``hops_home_at``
        without the turns further on): the best first move is the first heading (in heading
        order) whose safe move lands on the fewest moves home. Fields of the cell moves computed
        once per home and model, the turns where asked."""
        homes = np.asarray(homes_flat)
        rows = rows_reaching(
            self._hops, homes, (x, y), self._search("_reversed_hop_graph"), (1.0, 1.0),
            self._dead_ends, self.step, borrow=self._borrow("_hops"),
        ).reshape((-1,) + (1,) * (np.ndim(x) - 1))  # fmt: skip
        here = self._hops.take((rows, x, y))
        best = np.full(np.broadcast(rows, x, y).shape, np.inf)
        direction = np.zeros(best.shape, dtype=np.int64)
        for h in range(8):
            nx, ny = x + HEADING_STEPS[h][0], y + HEADING_STEPS[h][1]
            # a safe move ends inside the area: its landing cell is a cell of the field
            safe = self.home_edge_safe[h][x, y]
            nx, ny = np.where(safe, nx, x), np.where(safe, ny, y)
            after = np.where(safe, self._hops.take((rows, nx, ny)), np.inf)
            better = after < best
            best = np.where(better, after, best)
            direction = np.where(better, h, direction)
        diff = np.abs(np.asarray(headings) - direction)
        turns = np.maximum(np.minimum(diff, 8 - diff) - 1, 0)
        return here + np.where(here > 0, turns, 0).astype(float)

    @cached_property
    def _state_moves(self) -> np.ndarray:
        """(8, nx, ny): the moves of ``_state_neighbours`` by heading and cell: a move the
        planner may make (``home_edge_safe``), into a state with a way on (``viable``)."""
        return np.stack(
            [self.home_edge_safe[h] & self._shifted(self.viable[h], h) for h in range(8)]
        )

    @cached_property
    def _dead_end_states(self) -> np.ndarray:
        """(8, nx, ny): the (heading, cell) states no move of ``_state_neighbours`` leaves
        (none of the headings within phi_max has a move in ``_state_moves``)."""
        moves = self._state_moves
        return ~np.stack([np.any(moves[(h + self.turns) % 8], axis=0) for h in range(8)])

    @cached_property
    def _state_neighbours(self) -> np.ndarray:
        """The turn-limited safe moves between (heading, cell) states, state ``8 * flat + h``
        (a cell's states side by side: the search reads nearby memory): from (h, c) to (h',
        c + step(h')) for every h' within phi_max of h whose move from c is in
        ``home_edge_safe`` and lands in a viable state; reversed (the states a move *to* each
        state is made from, ``planner.breadth_first``: hops *to* a state)."""
        grid = self.grid
        size = grid.size
        flat = np.arange(size).reshape(grid.shape)
        table = neighbour_table(8 * size, len(self.turns))
        for h_next in range(8):
            start = flat[self._state_moves[h_next]]
            end = 8 * (start + grid.flat(HEADING_STEPS[h_next])) + h_next
            # the states it is reached from, one per turn, side by side
            table[end] = 8 * start[:, None] + (h_next - self.turns[None, :]) % 8
        return table


class SafetyModels:
    """The safety models of a swarm, one per set of known threats (a row of
    ``known_threats``), shared by the UAVs that know the same threats.

    A model holds fields per home for the UAVs that asked it (a few MB each on 200 x 200
    cells), and a UAV only ever learns threats: once no UAV has asked a model for a step, it is
    dropped (``drop_unused``). Should a UAV later come to know exactly those threats, the model
    is built again, the same: its fields are the same functions of the threats and the home,
    and its state searches are made as far as the dropped model's had been (a search's reach
    shows in the counts it returns), so decisions do not depend on what was dropped. 100 UAVs
    on 200 x 200 cells for 40 steps kept ten models of 50 homes each where one was asked. The
    models keep their fields in the stores of the first (``planner.field_pool``), each under
    a number of its own, so that a field one model frees is written again by another."""

    def __init__(self, make: Callable[[np.ndarray, dict[int, float] | None], SafetyModel]) -> None:
        """``make(known, searched)``: the model of the threats ``known`` (bool row)."""
        self._make = make
        self._models: dict[bytes, SafetyModel] = {}
        self._asked: dict[bytes, int] = {}  # model -> the last step it was asked at
        self._searched: dict[bytes, dict[int, float]] = {}  # dropped models' state searches
        self._swept = -1  # the step ``drop_unused`` last ran at
        self._pool: FieldPool | None = None  # the first model's stores, the others' too
        self._made = 0  # models made so far: a model's number in the stores

    def __len__(self) -> int:
        return len(self._models)

    def get(self, known: np.ndarray, step: int) -> SafetyModel:
        """The model of the threats ``known``, asked at decision step ``step``."""
        key = np.asarray(known, dtype=bool).tobytes()
        model = self._models.get(key)
        if model is None:
            model = self._models[key] = self._make(known, self._searched.pop(key, None))
            model.lenders = self._models.values  # no reference to the model: dropped, it goes
            self._pool = self._pool or model.pool
            model.use_pool(self._pool, self._made)
            self._made += 1
        self._asked[key] = max(step, self._asked.get(key, step))
        model.step = self._asked[key]
        return model

    def drop_unused(self, step: int) -> None:
        """Drop the models not asked at ``step`` nor the step before (the UAVs of a swarm
        planned node by node ask at the same step, each in turn), and the fields of the others
        not read as long (``SafetyModel.drop_unread``); once a step, however many UAVs' nodes
        share the models."""
        if step == self._swept:
            return
        self._swept = step
        for key in [k for k, asked in self._asked.items() if asked < step - 1]:
            model = self._models.pop(key)
            del self._asked[key]
            if model.state_limits:
                self._searched[key] = model.state_limits
        if self._pool is not None:
            self._pool.drop_unread(step)  # the fields of every model, kept or dropped
