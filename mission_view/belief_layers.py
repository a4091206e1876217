"""The heat layers of the view, from a ``planner.belief_snapshot.BeliefSnapshot``: the swarm's
coverage, and each UAV's target probability map (TPM) and pheromone map, downsampled to at most
``MAX_SIDE`` cells a side and quantised to one byte a cell.

Layer index: 0 the swarm's coverage; 1 .. N the TPM of UAV 0 .. N-1; N+1 .. 2N their pheromone.
Scales (fixed for a mission, so consecutive steps differ little and a replay compresses well):

* coverage: the share of each block's cells searched (as any UAV knows it), 0..255;
* TPM: the probability of a target in the block, ``1 - prod_layers (1 - min(1, m_l))`` with
  ``m_l`` the expected number of layer l's targets in the block (the sum of its cells, eq 16's
  scale applied; exact for layers of one target, an upper bound otherwise), on a log scale from
  ``TPM_FLOOR`` (0) to 1 (255). Summing the stored maps over blocks first makes this a quarter
  of the work of combining the layers cell by cell;
* pheromone: the block's mean tau, linear from tau_min (0) to tau_max (255) (eq 29).
"""

from __future__ import annotations

import math

import numpy as np

from planner.belief_snapshot import BeliefSnapshot
from planner.config import PlannerConfig

#: Largest side of a heat layer, in blocks (a 100 x 100 km area at 2 km a block).
MAX_SIDE = 50
#: Existence probabilities at or below this read as 0 on the TPM layer's log scale.
TPM_FLOOR = 1e-4

LAYER_KINDS = ("coverage", "tpm", "pheromone")

LAYER_SCALES = {
    "coverage": "share of the block searched, 0..1",
    "tpm": f"target existence probability, log scale {TPM_FLOOR:g}..1",
    "pheromone": "pheromone tau, tau_min..tau_max",
}


def block_size(nx: int, ny: int) -> int:
    return max(1, math.ceil(max(nx, ny) / MAX_SIDE))


def layer_shape(cfg: PlannerConfig) -> tuple[int, int]:
    b = block_size(cfg.grid_nx, cfg.grid_ny)
    return (math.ceil(cfg.grid_nx / b), math.ceil(cfg.grid_ny / b))


def layer_index(kind: str, uav: int, uav_count: int) -> int:
    if kind == "coverage":
        return 0
    if kind == "tpm":
        return 1 + uav
    if kind == "pheromone":
        return 1 + uav_count + uav
    raise ValueError(f"unknown layer kind {kind!r}; one of {', '.join(LAYER_KINDS)}")


def _block_reduce(maps: np.ndarray, b: int, fill: float, op: np.ufunc) -> np.ndarray:
    """(M, nx, ny) -> (M, bx, by): ``op`` (np.add or np.multiply) over each b x b block, the
    area padded with ``fill`` to whole blocks (strided slices: a reshape-and-reduce over two
    inner axes is several times slower)."""
    m, nx, ny = maps.shape
    bx, by = math.ceil(nx / b), math.ceil(ny / b)
    if (bx * b, by * b) != (nx, ny):
        maps = np.pad(maps, ((0, 0), (0, bx * b - nx), (0, by * b - ny)), constant_values=fill)
    out = maps[:, ::b, ::b].copy()
    for dx in range(b):
        for dy in range(b):
            if dx or dy:
                op(out, maps[:, dx::b, dy::b], out=out)
    return out


def _to_byte(values: np.ndarray) -> np.ndarray:
    return np.rint(np.clip(values, 0.0, 1.0) * 255.0).astype(np.uint8)


def quantise(snapshot: BeliefSnapshot, cfg: PlannerConfig) -> np.ndarray:
    """(2N + 1, bx, by) uint8 layers of ``snapshot`` (see the module docstring)."""
    n = snapshot.uav_count
    b = block_size(cfg.grid_nx, cfg.grid_ny)
    bx, by = layer_shape(cfg)
    out = np.zeros((2 * n + 1, bx, by), dtype=np.uint8)
    covered = _block_reduce(snapshot.swarm_coverage()[None].astype(np.float32), b, 0.0, np.add)
    out[0] = _to_byte(covered[0] / (b * b))
    if snapshot.tpm_maps is not None and snapshot.tpm_scale is not None:
        # expected targets of each layer in each block (the layers are expected counts, so a
        # block's is the sum of its cells'), scaled (eq 16), then combined across layers
        m, *_ = snapshot.tpm_maps.shape
        sums = _block_reduce(snapshot.tpm_maps.reshape(m * n, *snapshot.tpm_maps.shape[2:]),
                             b, 0.0, np.add)  # fmt: skip
        expected = sums.reshape(m, n, bx, by) * snapshot.tpm_scale[:, :, None, None]
        np.minimum(expected, 1.0, out=expected)
        p = 1.0 - np.prod(1.0 - expected, axis=0)
        log = (np.log10(np.maximum(p, TPM_FLOOR)) - math.log10(TPM_FLOOR)) / -math.log10(TPM_FLOOR)
        out[1 : n + 1] = _to_byte(log)
    if snapshot.pheromone is not None:
        tau = _block_reduce(snapshot.pheromone, b, cfg.tau_max, np.add) / (b * b)
        out[n + 1 :] = _to_byte((tau - cfg.tau_min) / max(cfg.tau_max - cfg.tau_min, 1e-12))
    return out
