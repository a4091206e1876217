"""A read-only copy of what the swarm believes after a decision step, for displays and replays.

The planner does no I/O: a viewer (``mission_view``) takes a ``BeliefSnapshot`` between steps and
works on it in its own thread while the planner goes on. The snapshot holds copies of each UAV's
target probability map layers (eqs 8-22, stored as ``TargetProbabilityMaps`` keeps them),
pheromone map (eqs 28-34) and the coverage it knows of; every array is marked read-only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner.belief_planner import beliefs_of
from planner.target_probability_map import existence_of_layers


def _frozen(array: np.ndarray, reuse: np.ndarray | None) -> np.ndarray:
    """A read-only copy of ``array``, written into ``reuse`` when it has the same shape and
    dtype (a buffer of an earlier snapshot that nobody reads any more: no fresh allocation)."""
    if reuse is not None and reuse.shape == array.shape and reuse.dtype == array.dtype:
        reuse.flags.writeable = True
        np.copyto(reuse, array)
        copy = reuse
    else:
        copy = np.array(array, copy=True)
    copy.flags.writeable = False
    return copy


@dataclass(frozen=True)
class BeliefSnapshot:
    """Beliefs of every UAV at decision step ``step`` (arrays are read-only copies)."""

    step: int
    coverage: np.ndarray  # (N, nx, ny) bool: cells UAV i knows as searched
    tpm_maps: np.ndarray | None  # (L, N, nx, ny) stored TPM layers, or None (no TPM)
    tpm_scale: np.ndarray | None  # (L, N) their scale (eq 16)
    pheromone: np.ndarray | None  # (N, nx, ny) tau, or None (no pheromone maps)

    @property
    def uav_count(self) -> int:
        return int(self.coverage.shape[0])

    def swarm_coverage(self) -> np.ndarray:
        """(nx, ny) bool: searched as any UAV knows it."""
        return self.coverage.any(axis=0)

    def existence(self, uav: int) -> np.ndarray | None:
        """UAV ``uav``'s target existence probability map p_mn (nx, ny), or None."""
        if self.tpm_maps is None or self.tpm_scale is None:
            return None
        return existence_of_layers(self.tpm_maps[:, uav], self.tpm_scale[:, uav])


@dataclass(frozen=True)
class CoverageBeliefs:
    """Beliefs known only as coverage: ``coverage`` (N, nx, ny) bool, the cells each UAV is
    known to have searched (what a ground station hears of the swarm's looks,
    ``mavlink_bridge.mission.swarm_watch``); no TPM, no pheromone."""

    coverage: np.ndarray


def belief_snapshot(
    planner: object, step: int, reuse: BeliefSnapshot | None = None
) -> BeliefSnapshot | None:
    """Copy the beliefs of a planner that keeps them in a ``SwarmBeliefs`` (HAPF-ACO, PSO,
    ACOAPF), or of a ``CoverageBeliefs``; None for one that keeps none. ``reuse``: a snapshot no
    longer read by anyone, whose arrays are overwritten instead of allocating new ones (the
    caller hands it over)."""
    if isinstance(planner, CoverageBeliefs):
        old = reuse.coverage if reuse is not None else None
        return BeliefSnapshot(step, _frozen(planner.coverage, old), None, None, None)
    beliefs = beliefs_of(planner)
    if beliefs is None:
        return None
    coverage, tpm = beliefs.coverage, beliefs.tpm
    pheromone = getattr(planner, "pheromone", None)
    old = reuse or BeliefSnapshot(step, coverage, None, None, None)
    return BeliefSnapshot(
        step=step,
        coverage=_frozen(coverage, old.coverage if reuse else None),
        tpm_maps=None if tpm is None else _frozen(tpm.maps, old.tpm_maps),
        tpm_scale=None if tpm is None else _frozen(tpm.scale, old.tpm_scale),
        pheromone=None if pheromone is None else _frozen(pheromone.tau, old.pheromone),
    )
