"""The sensor of section 3.1.2: distance-dependent detection probability (eq 17) and the
Bayesian cell update (eq 18).

One look of one UAV covers the cells whose centres lie within the detection radius R of the
UAV; each of them reports a detection bit b. The paper's b_k is one bit for the whole field of
view, with P_F the false alarm probability of a look; here a cell without a target reports
b = 1 with its share of it, ``cfg.cell_false_alarm`` (docs/parameters.md). The planner treats
eq 17's probability as the cell's P_D when it applies eq 18, with that share as the cell's P_F,
so a look at the edge of the footprint (where p(b=1|d) falls to it) carries no information,
and one straight below the UAV carries the most.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.config import PlannerConfig


@dataclass(frozen=True)
class SensorReport:
    """One look of one UAV's sensor: the cells in its footprint and a detection bit for each."""

    cells: np.ndarray  # (K, 2) int cells in the footprint
    detected: np.ndarray  # (K,) bool, b_k of eq 17 for each cell


def detection_probability(distance_km: np.ndarray | float, cfg: PlannerConfig) -> np.ndarray:
    """p(b_k = 1 | d_k) of eq 17 for the cell holding a target: P_D up to d_in, falling
    linearly to the cell's false alarm probability (``cfg.cell_false_alarm``) at d_out = R."""
    d = np.asarray(distance_km, dtype=float)
    d_in, d_out = cfg.sensor_d_in_km, cfg.detection_radius_km
    floor = cfg.cell_false_alarm
    ramp = cfg.p_detect - (cfg.p_detect - floor) * (d - d_in) / (d_out - d_in)
    return np.where(d <= d_in, cfg.p_detect, np.where(d <= d_out, ramp, floor))


def likelihood_ratio(
    detected: np.ndarray, p_detect: np.ndarray | float, p_false: float
) -> np.ndarray:
    """P(b | target) / P(b | no target) of one look at a cell: eq 18 multiplies a cell's odds
    of holding a target by it (P_D / P_F for b = 1, (1 - P_D) / (1 - P_F) for b = 0)."""
    pd = np.asarray(p_detect, dtype=float)
    with np.errstate(divide="ignore"):
        return np.where(detected, pd / p_false, (1.0 - pd) / (1.0 - p_false))


def posterior(prior: np.ndarray, ratio: np.ndarray) -> np.ndarray:
    """Eq 18 as an odds update: p' = p r / (1 - p + p r). Several looks at one cell combine by
    multiplying their ratios, exactly as applying eq 18 once per look."""
    p = np.minimum(np.maximum(prior, 0.0), 1.0)  # clip to [0, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        weighted = p * ratio
        out = weighted / (1.0 - p + weighted)
    bad = np.isnan(out)
    if bad.any():  # r = inf (P_F = 0): certain unless p = 0; p = 1 with r = 0 (P_D = 1): gone
        certain = np.broadcast_to(np.isinf(ratio), out.shape) & (np.broadcast_to(p, out.shape) > 0)
        out[bad] = certain[bad].astype(float)
    return out


def bayes_update(
    prior: np.ndarray, detected: np.ndarray, p_detect: np.ndarray | float, p_false: float
) -> np.ndarray:
    """Posterior existence probability of a cell after one look (eq 18, observed cases).

    ``detected`` true:  P_D p / (P_F + (P_D - P_F) p)
    ``detected`` false: (1 - P_D) p / (1 - P_F + (P_F - P_D) p)
    """
    return posterior(prior, likelihood_ratio(detected, p_detect, p_false))
