"""Distributed pheromone maps (section 3.3, eqs 28-34): one map per UAV, clamped to
[tau_min, tau_max] (eq 29), lowered around the predicted positions of the UAV and the swarm
members it knows of (eqs 30-33, an R^4 kernel) and raised everywhere at a fixed period (eq 34).

Symbols: tau^i -> ``PheromoneMaps.tau[i]``; delta tau_l0 -> ``cfg.local_decrement``; delta tau_g0 ->
``cfg.global_increment``; F -> ``cfg.uncertainty_factor``; R -> ``cfg.detection_radius_km``.
"""

from __future__ import annotations

import numpy as np

from planner.config import PlannerConfig
from planner.grid import Grid


def local_decrement_kernel(grid: Grid, cfg: PlannerConfig) -> tuple[np.ndarray, np.ndarray]:
    """Eq 33 on the grid: offsets (K, 2) within R and their decrement
    delta tau_l0 (R^4 - d^4)/R^4."""
    offsets = grid.disc_offsets(cfg.detection_radius_km)
    d = np.hypot(offsets[:, 0], offsets[:, 1]) * grid.cell_km
    r4 = cfg.detection_radius_km**4
    return offsets, cfg.local_decrement * (r4 - d**4) / r4


class PheromoneMaps:
    def __init__(self, n_uavs: int, cfg: PlannerConfig) -> None:
        self.cfg = cfg
        self.grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
        self.tau = np.full((n_uavs, cfg.grid_nx, cfg.grid_ny), cfg.tau_max)
        self.offsets, self.decrement = local_decrement_kernel(self.grid, cfg)

    def local_update(self, owners: np.ndarray, predicted_cells: np.ndarray) -> None:
        """Eqs 32-33: UAV ``owners[m]`` lowers its map around ``predicted_cells[m]``; pairs may
        repeat an owner (one pair per known swarm member). Then eq 29's clamp."""
        if len(owners) == 0:
            return
        cells = predicted_cells[:, None, :] + self.offsets[None, :, :]  # (M, K, 2)
        inside = self.grid.inside(cells)
        # one flat index into all the maps: owner's map, then cell
        index = (np.asarray(owners)[:, None] * self.grid.size + self.grid.flat(cells))[inside]
        amount = np.broadcast_to(self.decrement[None, :], inside.shape)[inside]
        view = self.tau.reshape(-1)
        np.subtract.at(view, index, amount)  # in order, so repeated cells add up as before
        # only lowered cells can leave [tau_min, tau_max]: clamp those (eq 29)
        view[index] = np.maximum(view[index], self.cfg.tau_min)

    def global_update(self) -> None:
        """Eq 34: tau += F delta tau_g0 on every cell of every map, then eq 29's clamp."""
        self.tau += self.cfg.uncertainty_factor * self.cfg.global_increment
        np.clip(self.tau, self.cfg.tau_min, self.cfg.tau_max, out=self.tau)

    def at(self, uavs: np.ndarray, cells: np.ndarray) -> np.ndarray:
        """Pheromone of UAV ``uavs`` (broadcast against cells.shape[:-1]) at ``cells``; outside the
        area reads tau_min."""
        values = self.tau.reshape(len(self.tau), -1)[uavs, self.grid.clipped_flat(cells)]
        return np.where(self.grid.inside(cells), values, self.cfg.tau_min)
