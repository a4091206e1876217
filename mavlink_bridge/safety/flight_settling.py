"""Settling the UAVs' guided targets one after another, kept apart from those settled before.

The flight-path layer (``flight_envelope.py``) has judged every candidate target of every UAV
(its threat clearance, and the instants its predicted path is kept apart at). UAVs settle in
index order: each takes its first candidate that keeps the threat margin and stays
``min_separation_km + separation_margin_km`` from every UAV settled before it; when none does,
the one that breaks the rules least, and it re-opens the choice of the settled UAV it comes
closest to (:meth:`Settling.repair`). Separation is judged on tiers of paths: first every
lossy-link variant of each plane against every variant of the others (paced time), and where no
candidate can keep that, the prediction alone. A planner node's neighbours (``fixed``) are
settled first as they are given, and never re-opened: the node can only move its own plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def separation_km(path: np.ndarray, settled: list[np.ndarray]) -> float:
    """Smallest distance (km) between ``path`` and any settled path at the same instant, over
    every pair of their variants (each (V, T, 2): the kept-apart instants of the prediction and
    of its lossy-link variants)."""
    if not settled:
        return float(np.inf)
    gap = np.stack(settled)[:, :, None] - path[None, None]  # (S, V, V, T, 2)
    return float(np.hypot(gap[..., 0], gap[..., 1]).min())


@dataclass(frozen=True)
class Settling:
    """What each candidate row was judged to be, and the rules the UAVs settle by."""

    counts: list[int]  # candidates per UAV (0: inactive, nothing is sent)
    row_of: dict[tuple[int, int], int]  # the row of each (UAV, candidate index)
    clearance_km: np.ndarray  # (M,) each row's predicted distance to a threat edge
    threat_margin_km: float
    need_sep_km: float  # min_separation_km + separation_margin_km
    #: UAVs whose one candidate is given (a planner node's neighbours): settled first, as
    #: they are, never re-opened; the others are kept apart from them
    fixed: frozenset[int] = frozenset()
    #: the order the other UAVs settle in (default: index order)
    order: tuple[int, ...] | None = None

    @property
    def threat_ok(self) -> np.ndarray:
        """(M,) the rows that keep the threat margin."""
        return self.clearance_km >= self.threat_margin_km

    def settle(self, tiers: list[np.ndarray]) -> dict[int, int]:
        """UAV -> the index of its chosen candidate, settled in index order. Each UAV is tried
        against each tier of kept-apart paths (M, V, T, 2) in turn until it finds a safe
        candidate or a repair makes it one."""
        threat_ok = self.threat_ok
        chosen: dict[int, int] = {j: 0 for j in sorted(self.fixed) if self.counts[j]}
        order = range(len(self.counts)) if self.order is None else self.order
        for i in order:
            count = self.counts[i]
            if not count or i in self.fixed:
                continue
            for apart in tiers:
                score, chosen[i] = self._best(i, apart, chosen, threat_ok)
                if not np.isfinite(score) or self.repair(i, chosen, apart, threat_ok):
                    break
        return chosen

    def _best(
        self, i: int, apart: np.ndarray, chosen: dict[int, int], threat_ok: np.ndarray
    ) -> tuple[float, int]:
        """UAV ``i``'s first safe candidate next to those ``chosen`` (score inf), else the one
        that breaks the rules least (the larger of its threat and separation shortfalls)."""
        others = [apart[self.row_of[(j, k)]] for j, k in chosen.items()]
        best: tuple[float, int] | None = None
        for k in range(self.counts[i]):
            r = self.row_of[(i, k)]
            sep = separation_km(apart[r], others)
            if threat_ok[r] and sep >= self.need_sep_km:
                return (np.inf, k)
            score = min(self.clearance_km[r] - self.threat_margin_km, sep - self.need_sep_km)
            if best is None or score > best[0]:
                best = (score, k)
        assert best is not None
        return best

    def repair(
        self, i: int, chosen: dict[int, int], paths: np.ndarray, threat_ok: np.ndarray
    ) -> bool:
        """UAV ``i`` found no safe candidate next to the UAVs settled before it. Re-open the
        choice of the settled UAV it comes closest to, ``j``: the first pair of candidates (j's
        in its order, then i's) that are both clear of threats, of every other settled UAV and
        of each other replaces both choices (True). Without such a pair nothing changes."""
        row_of, need_sep = self.row_of, self.need_sep_km
        mine = paths[row_of[(i, chosen[i])]]
        rivals = [j for j in chosen if j != i and j not in self.fixed]
        if not rivals:
            return False
        j = min(rivals, key=lambda o: separation_km(mine, [paths[row_of[(o, chosen[o])]]]))
        rest = [paths[row_of[(o, ko)]] for o, ko in chosen.items() if o not in (i, j)]
        safe_i = [
            k
            for k in range(self.counts[i])
            if threat_ok[row_of[(i, k)]] and separation_km(paths[row_of[(i, k)]], rest) >= need_sep
        ]
        for kj in range(self.counts[j]):
            rj = row_of[(j, kj)]
            if not threat_ok[rj] or separation_km(paths[rj], rest) < need_sep:
                continue
            for ki in safe_i:
                if separation_km(paths[row_of[(i, ki)]], [paths[rj]]) >= need_sep:
                    chosen[i], chosen[j] = ki, kj
                    return True
        return False

    def closest_km(self, apart: np.ndarray, chosen: dict[int, int]) -> float:
        """Smallest distance (km) between any two chosen candidates' kept-apart paths (not
        between two ``fixed`` ones: no choice of this settling keeps those apart)."""
        free = [apart[self.row_of[(i, k)]] for i, k in chosen.items() if i not in self.fixed]
        given = [apart[self.row_of[(i, k)]] for i, k in chosen.items() if i in self.fixed]
        return min(
            (separation_km(path, free[a + 1 :] + given) for a, path in enumerate(free)),
            default=np.inf,
        )
