"""The simulator's own safety account: what really flew, judged at every physics tick.

Whatever the ground station believes, the simulator knows where every plane was. At every tick
it judges the scenario's threat circles (C_t: all of them, uploaded as a fence or not) and
d_min (C_c) among the airborne vehicles:

* a **threat entry** is a vehicle's first tick inside one or more threat circles after a tick
  outside all of them; ``min_threat_margin_km`` is the smallest distance to a threat edge seen
  (negative: how deep inside);
* a **separation breach** is a pair's first tick closer than d_min after a tick at d_min or
  more; ``min_separation_km`` the smallest pairwise distance seen.

Each is also counted per **flight mode group** of the vehicle(s) involved (``guided``,
``failsafe`` while a GCS failsafe is on, out of RTL; ``rtl``, in which a failsafe changes
nothing, as after a mission whose ground station has gone; ``other``: take-off, loiter, circle,
auto),
so a ground station's continuous account (``mavlink_bridge.safety.track_audit``) can be checked
against the truth. Printed in the simulator's JSON summary under ``safety``.
"""

from __future__ import annotations

import math

import numpy as np

#: in the order a pair of vehicles in two groups is counted under (most telling first)
GROUPS = ("failsafe", "rtl", "other", "guided")


class GroundTruthSafety:
    """Per-tick threat and separation account of one fleet."""

    def __init__(
        self, n: int, threat_xy_m: np.ndarray, threat_radius_m: np.ndarray, min_separation_m: float
    ) -> None:
        self.n = n
        self.threat_xy = np.asarray(threat_xy_m, float).reshape(-1, 2)
        self.threat_r = np.asarray(threat_radius_m, float).reshape(-1)
        self.min_separation_m = float(min_separation_m)
        self.inside = np.zeros(n, bool)
        self.close = np.zeros((n, n), bool)
        self.iu = np.triu_indices(n, 1)
        self.entries = dict.fromkeys(GROUPS, 0)
        self.breaches = dict.fromkeys(GROUPS, 0)
        self.margin_m = dict.fromkeys(GROUPS, math.inf)
        self.separation_m = dict.fromkeys(GROUPS, math.inf)
        self.closest: tuple[int, int, float] | None = None  # UAV indices, sim time

    def observe(
        self, t_s: float, x_m: np.ndarray, y_m: np.ndarray, airborne: np.ndarray, group: np.ndarray
    ) -> None:
        """One tick: positions (N,) in metres, which vehicles fly, each one's ``GROUPS`` index."""
        group = np.asarray(group, np.int64)
        if len(self.threat_r):
            dx = x_m[:, None] - self.threat_xy[None, :, 0]
            dy = y_m[:, None] - self.threat_xy[None, :, 1]
            margin = (np.hypot(dx, dy) - self.threat_r[None]).min(axis=1)
            margin = np.where(airborne, margin, np.inf)
            inside = margin < 0
            for i in np.flatnonzero(inside & ~self.inside):
                self.entries[GROUPS[group[i]]] += 1
            self.inside = inside
            self._lowest(self.margin_m, margin, group)
        if self.n < 2:
            return
        i, j = self.iu
        d = np.where(airborne[i] & airborne[j], np.hypot(x_m[i] - x_m[j], y_m[i] - y_m[j]), np.inf)
        pair_group = np.minimum(group[i], group[j])
        close = d < self.min_separation_m
        for k in np.flatnonzero(close & ~self.close[i, j]):
            self.breaches[GROUPS[pair_group[k]]] += 1
        self.close[i, j] = close
        k = int(np.argmin(d))
        if d[k] < min(self.separation_m.values()):
            self.closest = (int(i[k]), int(j[k]), float(t_s))
        self._lowest(self.separation_m, d, pair_group)

    @staticmethod
    def _lowest(best: dict[str, float], values: np.ndarray, group: np.ndarray) -> None:
        for g, name in enumerate(GROUPS):
            mine = values[group == g]
            if mine.size and mine.min() < best[name]:
                best[name] = float(mine.min())

    def summary(self) -> dict:
        def km(m: float) -> float | None:
            return None if not math.isfinite(m) else round(m / 1000.0, 4)

        return {
            "source": "simulator ground truth, every physics tick",
            "threat_entries": sum(self.entries.values()),
            "min_threat_margin_km": km(min(self.margin_m.values())),
            "separation_breaches": sum(self.breaches.values()),
            "min_separation_km": km(min(self.separation_m.values())),
            "closest_pair_uavs": None if self.closest is None else list(self.closest[:2]),
            "closest_at_s": None if self.closest is None else round(self.closest[2], 1),
            "by_mode": {
                name: {
                    "threat_entries": self.entries[name],
                    "min_threat_margin_km": km(self.margin_m[name]),
                    "separation_breaches": self.breaches[name],
                    "min_separation_km": km(self.separation_m[name]),
                }
                for name in GROUPS
            },
        }
