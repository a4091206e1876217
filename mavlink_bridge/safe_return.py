"""The way home clear of threats: when a plane may fly RTL, and where it flies until then.

ArduPlane's RTL flies the straight line to home (or a rally point) and a fence breach in RTL
changes nothing, so a plane on the far side of a threat circle flies right through it (issue
12: the simulator's ground truth saw a return 0.67 km deep in a threat with 0 violations
reported). The daemon therefore sends RTL only to a plane whose way home is clear
(:meth:`HomeRoutes.rtl_clear`):

* the straight line from where it is to its home keeps ``margin_km`` from every threat circle
  (C_t of the paper's constraint set, with the envelope's margin), and
* the path it flies there, turning from its present course at its turn rate
  (``flight_prediction.predict_paths``), keeps ``turn_margin_km``.

Any other plane is guided (DO_REPOSITION) to a **waypoint** on the shortest way home around
the threats, and re-judged every decision period until RTL is clear. The way is a shortest path
over the grid's cell centres that keep ``margin_km`` plus the plane's loiter reach (a loiter
diameter: it passes the point before it turns onto its circle) from every threat (a plane whose
ground station goes silent circles its last guided target, so each waypoint is a safe place to
circle), joined by 8-neighbour legs that keep ``margin_km``;
the waypoint sent is the farthest one along that path in straight-line reach (a leg that keeps
``margin_km``) of where the plane is, so the plane cuts corners the grid would make it fly.

Distances from home over the graph are computed once per home (``scipy.sparse.csgraph``); a
query joins the plane's position to every node in reach in one vectorised clearance test.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from mavlink_bridge.flight_prediction import PlaneModel, predict_paths
from planner.constraints import segment_clearance
from planner.grid import Grid

#: the eight neighbour offsets of a cell (the grid's headings)
_NEIGHBOURS = np.array([(1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1)])


@dataclass
class _FromHome:
    """Shortest distances over the waypoint graph to one home, and the next node towards it."""

    distance_km: np.ndarray  # (nodes,) inf where home is out of reach
    towards: np.ndarray  # (nodes,) next node index towards home, -1: home itself is next


@dataclass
class HomeRoutes:
    """Safe ways home through one scenario's threats for one airframe."""

    grid: Grid
    threat_xy_km: np.ndarray  # (M, 2)
    threat_radius_km: np.ndarray  # (M,)
    plane: PlaneModel
    margin_km: float = 1.0  # legs (and the straight line home) keep this from every threat
    turn_margin_km: float = 0.25  # the predicted turn onto the way home keeps this
    _nodes_km: np.ndarray | None = field(init=False, default=None, repr=False)
    _edges: coo_matrix | None = field(init=False, default=None, repr=False)
    _homes: dict[tuple[float, float], _FromHome] = field(init=False, default_factory=dict)

    def _build(self) -> None:
        """The waypoint graph, built at the first way asked for (a mission whose planes all
        have a clear line home never needs it; paper-10uav: 9,460 nodes in ~0.2 s)."""
        g = self.grid
        ix, iy = np.meshgrid(np.arange(g.nx), np.arange(g.ny), indexing="ij")
        cells = np.stack([ix.ravel(), iy.ravel()], axis=1)
        centres = g.centre_km(cells)
        loiter_km = float(self.plane.loiter_reach_km())
        keep = self.point_clearance(centres) >= self.margin_km + loiter_km
        self._nodes_km = centres[keep]
        index = np.full(g.nx * g.ny, -1)
        index[np.flatnonzero(keep)] = np.arange(int(keep.sum()))
        kept = cells[keep]
        rows, cols, lengths = [], [], []
        for dx, dy in _NEIGHBOURS:
            other = kept + (dx, dy)
            inside = (other[:, 0] >= 0) & (other[:, 0] < g.nx) & (other[:, 1] >= 0)
            inside &= other[:, 1] < g.ny
            j = np.full(len(kept), -1)
            j[inside] = index[other[inside, 0] * g.ny + other[inside, 1]]
            i = np.flatnonzero(j >= 0)
            j = j[i]
            clear = self.leg_clearance(self._nodes_km[i], self._nodes_km[j]) >= self.margin_km
            rows.append(i[clear])
            cols.append(j[clear])
            lengths.append(np.hypot(dx, dy) * g.cell_km * np.ones(int(clear.sum())))
        n = len(self._nodes_km)
        self._edges = coo_matrix(
            (np.concatenate(lengths), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
        )

    # ------------------------------------------------------------------ geometry

    def point_clearance(self, xy_km: np.ndarray) -> np.ndarray:
        """Per point (N, 2): distance to the nearest threat circle's edge (< 0: inside)."""
        if len(self.threat_radius_km) == 0:
            return np.full(len(xy_km), np.inf)
        d = np.hypot(*(xy_km[:, None, :] - self.threat_xy_km[None]).transpose(2, 0, 1))
        return (d - self.threat_radius_km[None]).min(axis=1)

    def leg_clearance(self, a_km: np.ndarray, b_km: np.ndarray) -> np.ndarray:
        """Per straight leg ``a``-``b`` (..., 2): its distance to the nearest threat edge."""
        return segment_clearance(a_km, b_km, self.threat_xy_km, self.threat_radius_km)

    def line_clear(self, a_km: np.ndarray, b_km: np.ndarray) -> bool:
        """The straight leg ``a``-``b`` keeps ``margin_km`` from every threat."""
        return bool(self.leg_clearance(np.asarray(a_km, float), np.asarray(b_km, float))
                    >= self.margin_km)  # fmt: skip

    def rtl_clear(self, xy_km: np.ndarray, course_rad: float, home_km: np.ndarray) -> bool:
        """RTL from ``xy_km`` flying ``course_rad`` keeps clear of every threat: the straight
        line home by ``margin_km`` and the turn onto it, as the plane flies it, by
        ``turn_margin_km``."""
        xy, home = np.asarray(xy_km, float), np.asarray(home_km, float)
        if not self.line_clear(xy, home):
            return False
        if len(self.threat_radius_km) == 0:
            return True
        return bool(self.turn_clearance(xy, course_rad, home[None])[0] >= self.turn_margin_km)

    # ------------------------------------------------------------------ routes

    def _from_home(self, home_km: np.ndarray) -> _FromHome:
        key = (round(float(home_km[0]), 3), round(float(home_km[1]), 3))
        known = self._homes.get(key)
        if known is not None:
            return known
        assert self._nodes_km is not None and self._edges is not None
        n = len(self._nodes_km)
        reach = self.leg_clearance(np.broadcast_to(home_km, (n, 2)), self._nodes_km)
        to_home = np.flatnonzero(reach >= self.margin_km)
        length = np.hypot(*(self._nodes_km[to_home] - home_km).T)
        # node n is home; the graph is undirected, so distances from home are distances to it
        rows = np.concatenate([self._edges.row, to_home, np.full(len(to_home), n)])
        cols = np.concatenate([self._edges.col, np.full(len(to_home), n), to_home])
        data = np.concatenate([self._edges.data, length, length])
        graph = coo_matrix((data, (rows, cols)), shape=(n + 1, n + 1)).tocsr()
        distance, previous = dijkstra(graph, directed=False, indices=n, return_predecessors=True)
        towards = np.where(previous[:n] == n, -1, previous[:n])
        known = _FromHome(distance[:n], towards)
        self._homes[key] = known
        return known

    def waypoint(
        self, xy_km: np.ndarray, home_km: np.ndarray, course_rad: float | None = None
    ) -> np.ndarray | None:
        """The next safe waypoint (km) on the shortest way from ``xy_km`` home around the
        threats, and one whose turn from ``course_rad`` (if given) keeps ``turn_margin_km``;
        ``None`` when RTL is clear (or no way is known: a plane cut off by threats is left to
        RTL). A plane inside a threat circle takes legs that get no deeper: the way out."""
        xy, home = np.asarray(xy_km, float), np.asarray(home_km, float)
        if self.line_clear(xy, home) and (
            course_rad is None or self.rtl_clear(xy, course_rad, home)
        ):
            return None
        ways = self._ways(xy, home)
        if ways is None:
            return None
        assert self._nodes_km is not None
        paths, reach, total = ways
        first = int(np.argmin(total))
        if not math.isfinite(total[first]):
            return None
        node = first  # then on along the way while still in straight reach
        while paths.towards[node] >= 0 and reach[paths.towards[node]]:
            node = int(paths.towards[node])
        if course_rad is None or self.turn_clearance(xy, course_rad, self._nodes_km[[node]])[0] >= (
            self.turn_margin_km
        ):
            return self._nodes_km[node].copy()
        # the turn onto that leg sweeps too close: the cheapest node whose turn is clear, or
        # (a plane too near a threat for any turn to keep the margin) the one whose turn keeps most
        order = np.argsort(total)[: int(np.isfinite(total).sum())][:64]
        turns = self.turn_clearance(xy, course_rad, self._nodes_km[order])
        clear = turns >= self.turn_margin_km
        best = int(np.argmax(clear)) if clear.any() else int(np.argmax(turns))
        return self._nodes_km[order[best]].copy()

    def way_length_km(self, xy_km: np.ndarray, home_km: np.ndarray) -> float:
        """Length of the safe way home from ``xy_km``: the straight line where it keeps
        ``margin_km``, else the shortest way through the waypoints (``inf``: none known)."""
        xy, home = np.asarray(xy_km, float), np.asarray(home_km, float)
        if self.line_clear(xy, home):
            return float(np.hypot(*(home - xy)))
        ways = self._ways(xy, home)
        return math.inf if ways is None else float(ways[2].min())

    def _ways(
        self, xy: np.ndarray, home: np.ndarray
    ) -> tuple[_FromHome, np.ndarray, np.ndarray] | None:
        """The waypoints towards ``home`` and, per waypoint, whether ``xy`` reaches it in a
        straight leg and the length of the way home through it (None: no waypoint at all)."""
        if self._nodes_km is None:
            self._build()
        assert self._nodes_km is not None
        if len(self._nodes_km) == 0:
            return None
        paths = self._from_home(home)
        n = len(self._nodes_km)
        # a plane already nearer a threat than the margin (or inside it: a fence breach) takes
        # legs that get no nearer
        need = min(self.margin_km, float(self.point_clearance(xy[None])[0]) - 1e-6)
        reach = self.leg_clearance(np.broadcast_to(xy, (n, 2)), self._nodes_km) >= need
        total = np.where(reach, np.hypot(*(self._nodes_km - xy).T) + paths.distance_km, np.inf)
        return paths, reach, total

    def turn_clearance(self, xy: np.ndarray, course_rad: float, aims: np.ndarray) -> np.ndarray:
        """Per aim: threat clearance of the path a plane at ``xy`` flying ``course_rad`` flies
        while it turns towards the aim (half a circle at its turn rate: any turn)."""
        if len(self.threat_radius_km) == 0:
            return np.full(len(aims), np.inf)
        m = len(aims)
        turn_s = math.pi / float(self.plane.turn_rate_radps())
        paths = predict_paths(
            self.plane, np.repeat(xy[None], m, 0), np.full(m, course_rad), aims, turn_s
        )
        return self.point_clearance(paths.reshape(-1, 2)).reshape(m, -1).min(axis=1)
