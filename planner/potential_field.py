"""Artificial potential field (section 3.2, eqs 23-27): TPM attraction, threat repulsion and
generalized-Morse repulsion between UAVs, evaluated at any set of points for every UAV at once.

Symbols: k_att -> ``cfg.k_att``; k_rep -> ``cfg.k_rep``; d_0 -> threat radius +
``cfg.threat_margin_km``;
d^t_max -> threat radius + R (a threat is felt once detected, section 3.2.2); b, c ->
``cfg.morse_b``, ``cfg.morse_c_km``; ||x||_min -> ``cfg.morse_r0_km``; [d_min, d^v_max] ->
``cfg.min_separation_km``, ``cfg.uav_repulsion_range_km``.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from planner.config import PlannerConfig


def attraction(existence: np.ndarray, cfg: PlannerConfig) -> np.ndarray:
    """Eqs 23-24: k_att times the gradient of the TPM at the centre of a 3x3 patch.

    ``existence`` is (..., 3, 3) existence probabilities around each point (x first axis);
    returns (..., 2) forces (per km) by central differences."""
    gx = (existence[..., 2, 1] - existence[..., 0, 1]) / 2.0
    gy = (existence[..., 1, 2] - existence[..., 1, 0]) / 2.0
    return cfg.k_att * np.stack([gx, gy], axis=-1) / cfg.cell_km


def threat_repulsion(
    points_km: np.ndarray,
    threat_xy: np.ndarray,
    threat_r: np.ndarray,
    known: np.ndarray,
    cfg: PlannerConfig,
) -> np.ndarray:
    """Eq 25 for points (N, K, 2) and the threats each UAV knows (``known`` (N, T) bool).

    The paper's ``1/||x||^2 - 1/(d_max - d_0)^2`` turns attractive near d_max; we measure the
    distance from the safe boundary d_0 (docs/parameters.md): ``k_rep (1/(||x|| - d_0)^2 -
    1/(d_max - d_0)^2)`` for d_0 < ||x|| <= d_max, pointing away from the threat.

    Only the UAVs whose points can be within d_max of a threat they know are evaluated; the
    others feel no force (exact zeros)."""
    force = np.zeros(points_km.shape)
    if threat_xy.size == 0:
        return force
    d_max = threat_r + cfg.detection_radius_km
    anchor = points_km[:, :1, :]  # (N, 1, 2): every point lies within ``spread`` of it
    spread = np.hypot(*(points_km - anchor).transpose(2, 0, 1)).max(initial=0.0)
    reach = np.hypot(*(anchor - threat_xy[None, :, :]).transpose(2, 0, 1))  # (N, T)
    felt = (known & (reach <= d_max[None, :] + spread + 1e-6)).any(axis=1)
    if felt.any():
        force[felt] = _threat_force(points_km[felt], threat_xy, threat_r, known[felt], cfg)
    return force


def _threat_force(
    points_km: np.ndarray,
    threat_xy: np.ndarray,
    threat_r: np.ndarray,
    known: np.ndarray,
    cfg: PlannerConfig,
) -> np.ndarray:
    """Eq 25 (as ``threat_repulsion`` reads it) at points (M, K, 2) from every threat."""
    x = points_km[:, :, None, :] - threat_xy[None, None, :, :]  # (M, K, T, 2)
    dist = np.maximum(np.hypot(x[..., 0], x[..., 1]), 1e-9)
    d0 = threat_r + cfg.threat_margin_km
    d_max = threat_r + cfg.detection_radius_km
    gap = np.maximum(dist - d0[None, None, :], 1e-3)
    magnitude = cfg.k_rep * (1.0 / gap**2 - 1.0 / (d_max - d0)[None, None, :] ** 2)
    magnitude = np.where(
        (dist <= d_max[None, None, :]) & known[:, None, :], np.maximum(magnitude, 0), 0.0
    )
    return np.sum(magnitude[..., None] * x / dist[..., None], axis=2)


def morse_repulsion(
    points_km: np.ndarray,
    others_km: np.ndarray,
    neighbours: np.ndarray,
    cfg: PlannerConfig,
    own_km: np.ndarray | None = None,
) -> np.ndarray:
    """Eq 27: F = sum_j (b/c) e^{||x||/c} / (e^{||x||/c} - e^{r0/c})^2 x_hat over neighbours j
    with ||x_ij|| in [d_min, d^v_max] (closer than d_min it is held at its d_min value).

    ``points_km`` (n, K, 2) around each of n UAVs at ``own_km`` (n, 2; None: ``others_km``),
    ``others_km`` (N, 2) the swarm's positions, ``neighbours`` (n, N) bool. Only the (i, j)
    pairs that can be in range are evaluated."""
    own_km = others_km if own_km is None else own_km
    force = np.zeros(points_km.shape)
    spread = np.hypot(*(points_km - own_km[:, None, :]).transpose(2, 0, 1)).max(initial=0.0)
    diff = own_km[:, None, :] - others_km[None, :, :]
    gap = np.hypot(diff[..., 0], diff[..., 1])
    owner, other = np.nonzero(neighbours & (gap <= cfg.uav_repulsion_range_km + spread))
    if owner.size == 0:
        return force
    x = points_km[owner] - others_km[other][:, None, :]  # (P, K, 2)
    dist = np.hypot(x[..., 0], x[..., 1])
    c, r0 = cfg.morse_c_km, cfg.morse_r0_km
    d = np.maximum(dist, cfg.min_separation_km)
    magnitude = (cfg.morse_b / c) * np.exp(d / c) / (np.exp(d / c) - np.exp(r0 / c)) ** 2
    magnitude = np.where((dist <= cfg.uav_repulsion_range_km) & (dist > 1e-9), magnitude, 0.0)
    push = magnitude[..., None] * x / np.maximum(dist, 1e-9)[..., None]
    np.add.at(force, owner, push)
    return force


@lru_cache(maxsize=4)
def far_weights(nx: int, ny: int, cell_km: float, block_cells: int, length_km: float) -> np.ndarray:
    """``exp(-d / length_km)`` from every cell (flat index) to the centre of every block of
    ``block_cells`` x ``block_cells`` cells, (nx * ny, B) float32: the kernel of the far
    attraction (``far_potential``), computed once per grid."""
    bx, by = -(-nx // block_cells), -(-ny // block_cells)
    cx = (np.arange(bx) + 0.5) * block_cells - 0.5
    cy = (np.arange(by) + 0.5) * block_cells - 0.5
    gx = np.arange(nx)[:, None] - cx[None, :]  # (nx, bx)
    gy = np.arange(ny)[:, None] - cy[None, :]  # (ny, by)
    d = np.hypot(gx[:, None, :, None], gy[None, :, None, :]) * cell_km  # (nx, ny, bx, by)
    weights = np.exp(-d / length_km).astype(np.float32).reshape(nx * ny, bx * by)
    weights.setflags(write=False)
    return weights


def block_masses(
    maps: np.ndarray, scale: np.ndarray, block_cells: int, keep: np.ndarray | None = None
) -> np.ndarray:
    """Expected number of targets in each block of ``block_cells`` x ``block_cells`` cells, per
    UAV: ``maps`` (L, N, nx, ny) stored TPM layers, ``scale`` (L, N) their scales
    (``TargetProbabilityMaps``), counting only the cells ``keep`` (N, nx, ny) bool marks;
    returns (N, B)."""
    _, n, nx, ny = maps.shape
    expected = np.einsum("lnxy,ln->nxy", maps, scale.astype(np.float32))  # (N, nx, ny)
    if keep is not None:
        expected *= keep
    b = block_cells
    bx, by = -(-nx // b), -(-ny // b)
    if (bx * b, by * b) != (nx, ny):
        expected = np.pad(expected, ((0, 0), (0, bx * b - nx), (0, by * b - ny)))
    return expected.reshape(n, bx, b, by, b).sum(axis=(2, 4), dtype=np.float64).reshape(n, -1)


def far_potential(weights: np.ndarray, masses: np.ndarray, flat_cells: np.ndarray) -> np.ndarray:
    """The attraction field of eq 23 smoothed over the far kernel: ``sum_b m_b exp(-d_b / L)``
    at cells (flat indices (N, C)) for each UAV's block masses (N, B). Its differences between
    points far from any TPM peak point toward distant probability mass, where the gradient of
    eq 24 at the UAV's own cell is near zero."""
    return np.einsum("ncb,nb->nc", weights[flat_cells], masses.astype(np.float32))
