"""Target priors (section 3.1, eqs 9-16): the initial map of each kind of target, and how
targets share the maps' layers.

How several targets share one map (the paper is silent): the map is split into *layers*, one
per group of targets that move under the same forecast kernel (all unknown-position targets;
all known-position targets; known-speed targets of one speed; each known-velocity target). A
layer holds the expected number of its targets in each cell, so it sums to the number of its
targets still at large (``planner.target_probability_map``).

Symbols: delta_0 -> ``cfg.delta_0_km``; delta_e -> ``cfg.delta_e_km_per_sqrt_s``; t_0 ->
``cfg.t0_s``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from planner.config import PlannerConfig
from planner.grid import Grid
from planner.scenario import TargetSpec

#: Quadrature sizes for the ring integrals and the cell-to-cell motion kernels.
RING_ANGLES = 128
CELL_SAMPLES = 16


# ----------------------------------------------------------------------------- initialisation


def _cell_gaussian_mass(
    centre_x: np.ndarray, centre_y: np.ndarray, sigma: float, grid: Grid
) -> np.ndarray:
    """Mass of isotropic Gaussians N(centre, sigma^2) in each cell, integrated exactly (eq 15).

    ``centre_x``/``centre_y`` are (A,) arrays; the result is (nx, ny), the average over the A
    Gaussians (the A points of a ring quadrature, or one point)."""
    edges_x = np.arange(grid.nx + 1) * grid.cell_km
    edges_y = np.arange(grid.ny + 1) * grid.cell_km
    cdf_x = ndtr((edges_x[None, :] - np.asarray(centre_x)[:, None]) / sigma)  # (A, nx+1)
    cdf_y = ndtr((edges_y[None, :] - np.asarray(centre_y)[:, None]) / sigma)
    mass_x = np.diff(cdf_x, axis=1)  # (A, nx)
    mass_y = np.diff(cdf_y, axis=1)
    return np.einsum("ai,aj->ij", mass_x, mass_y) / len(mass_x)


def uniform_prior(grid: Grid) -> np.ndarray:
    """Eq 9: unknown position, the same probability in every cell."""
    return np.full(grid.shape, 1.0 / grid.size)


def wiener_prior(target: TargetSpec, cfg: PlannerConfig, grid: Grid) -> np.ndarray:
    """Eq 11: known position, unknown velocity; N(x*, delta_0^2 + delta_e^2 t_0)."""
    sigma = np.sqrt(cfg.delta_0_km**2 + cfg.delta_e_km_per_sqrt_s**2 * cfg.t0_s)
    return _cell_gaussian_mass(np.array([target.x_km]), np.array([target.y_km]), sigma, grid)


def ring_prior(target: TargetSpec, cfg: PlannerConfig, grid: Grid) -> np.ndarray:
    """Eqs 12-13: known speed v, unknown heading; the Gaussian of eq 10 averaged over the circle
    of radius v t_0 around x* (angular quadrature, each Gaussian integrated over cells)."""
    radius = target.speed_mps / 1000.0 * cfg.t0_s
    theta = (np.arange(RING_ANGLES) + 0.5) * (2 * np.pi / RING_ANGLES)
    return _cell_gaussian_mass(
        target.x_km + radius * np.cos(theta),
        target.y_km + radius * np.sin(theta),
        cfg.delta_0_km,
        grid,
    )


def shifted_prior(target: TargetSpec, cfg: PlannerConfig, grid: Grid) -> np.ndarray:
    """Eq 14: known velocity; N(x* + v t_0 (cos theta, sin theta), delta_0^2)."""
    shift = target.speed_mps / 1000.0 * cfg.t0_s
    return _cell_gaussian_mass(
        np.array([target.x_km + shift * np.cos(target.heading_rad)]),
        np.array([target.y_km + shift * np.sin(target.heading_rad)]),
        cfg.delta_0_km,
        grid,
    )


def normalised(mass: np.ndarray) -> np.ndarray:
    """Eq 16: divide by the total so the map sums to one."""
    return mass / mass.sum()


# ----------------------------------------------------------------------------- layers


@dataclass(frozen=True)
class LayerSpec:
    """A group of targets that share a forecast kernel (one layer of the TPM)."""

    kind: str  # one of planner.scenario.TARGET_KINDS
    target_ids: tuple[int, ...]
    mean_value: float
    speed_mps: float = 0.0
    heading_rad: float = 0.0


def layer_specs(targets: tuple[TargetSpec, ...]) -> list[LayerSpec]:
    """Group the scenario's targets into layers that move alike."""
    groups: dict[tuple, list[TargetSpec]] = {}
    for t in targets:
        if t.kind in ("unknown_position", "known_position"):
            key: tuple = (t.kind,)
        elif t.kind == "known_speed":
            key = (t.kind, t.speed_mps)
        else:
            key = (t.kind, t.id)
        groups.setdefault(key, []).append(t)
    specs = []
    for members in groups.values():
        first = members[0]
        specs.append(
            LayerSpec(
                kind=first.kind,
                target_ids=tuple(m.id for m in members),
                mean_value=float(np.mean([m.value for m in members])),
                speed_mps=first.speed_mps,
                heading_rad=first.heading_rad,
            )
        )
    return specs


def initial_layers(
    targets: tuple[TargetSpec, ...], cfg: PlannerConfig
) -> tuple[list[LayerSpec], np.ndarray]:
    """Eqs 9-16 for every target, summed into layers: ``(specs, maps (L, nx, ny))``; each
    target contributes a normalised map, so layer l sums to its number of targets."""
    grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
    prior_of = {
        "unknown_position": lambda t: uniform_prior(grid),
        "known_position": lambda t: wiener_prior(t, cfg, grid),
        "known_speed": lambda t: ring_prior(t, cfg, grid),
        "known_velocity": lambda t: shifted_prior(t, cfg, grid),
    }
    by_id = {t.id: t for t in targets}
    specs = layer_specs(targets)
    maps = np.zeros((len(specs), grid.nx, grid.ny))
    for index, spec in enumerate(specs):
        for tid in spec.target_ids:
            maps[index] += normalised(prior_of[spec.kind](by_id[tid]))
    return specs, maps

