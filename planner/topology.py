"""Dynamic neighbour topology (section 2.2, eqs 1-3).

Each UAV i hears the UAVs within its cooperative radius ``r_coor[i]`` (eq 1, the adjacency of
eq 3); the radius is adapted every step toward ``n_topo`` neighbours (eq 2, integrated with one
Euler step per decision period) and kept in ``[coop_radius_min_km, R_sen]``.

Symbols: r_i^coor -> ``radius_km``; k -> ``cfg.topology_rate``; R_sen -> ``cfg.sensing_radius_km``;
n_topo -> ``cfg.n_topo``; a_ij -> ``adjacency``.
"""

from __future__ import annotations

import numpy as np

from planner.config import PlannerConfig


def pairwise_distances(positions_km: np.ndarray) -> np.ndarray:
    """(N, N) Euclidean distances d_ij."""
    diff = positions_km[:, None, :] - positions_km[None, :, :]
    return np.hypot(diff[..., 0], diff[..., 1])


def adjacency(distances_km: np.ndarray, radius_km: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Eqs 1 and 3: a_ij = 1 when d_ij <= r_i^coor, j != i, both UAVs active."""
    a = distances_km <= radius_km[:, None]
    np.fill_diagonal(a, False)
    return a & active[:, None] & active[None, :]


def adapt_radius(
    radius_km: np.ndarray, neighbour_counts: np.ndarray, cfg: PlannerConfig
) -> np.ndarray:
    """Eq 2: r_dot = k R_sen (1 - |N_i| / n_topo), one step of one decision period."""
    rate = cfg.topology_rate * cfg.sensing_radius_km * (1.0 - neighbour_counts / cfg.n_topo)
    return np.clip(radius_km + rate, cfg.coop_radius_min_km, cfg.sensing_radius_km)
