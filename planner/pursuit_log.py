"""What the planner believed and did about targets, step by step: the planner's half of the
per-target account (``sim_gateway.target_account`` holds the ground-truth half and joins them).

The log reads the planner's state, never writes it, and never sees ground truth: it records, at
each decision step after the planner decided and before it forecast its beliefs (eqs 19-22):

- **belief peaks**: the probability that a target lies within the engage radius of a cell
  (``SwarmBeliefs.engage_probability``, section 3.2.1, from the TPM of eqs 16-18), at the
  cells of each flying UAV's own sensor footprint and at the cell it pursues, as that UAV
  believes it; a cell's entry is the highest over the UAVs and is kept when it reaches
  ``floor`` (a target never looked at keeps its prior, far below it);
- **pursuits**: the cell each UAV goes for (``SwarmBeliefs.track``) and whether its target
  counts as confirmed there (``track_confirmed``);
- **engagement requests**: which UAVs asked for an engagement at that step.

Cells are grid indices; the join places them with the grid's cell size. Attach with
``PursuitLog.attach(planner)``: the planner's beliefs (``planner.swarm_beliefs.SwarmBeliefs``)
call ``record`` at every step (their ``observers``); a planner without them logs nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planner.belief_planner import beliefs_of
from planner.swarm_beliefs import SwarmBeliefs

#: Belief below this is not logged (the account's peak reads 0 for a target never above it).
BELIEF_FLOOR = 0.05


@dataclass
class PursuitLog:
    """Per-step belief, pursuit and engagement-request facts of one planner (read-only)."""

    floor: float = BELIEF_FLOOR
    beliefs: list[list[float]] = field(default_factory=list)  # [step, cx, cy, p]
    tracks: list[list[int]] = field(default_factory=list)  # [step, uav, cx, cy, confirmed]
    engage_requests: list[list[int]] = field(default_factory=list)  # [step, uav]
    cell_km: float = 1.0

    def attach(self, planner) -> PursuitLog:
        """Record every step of ``planner`` from now on (nothing for a planner that keeps no
        ``SwarmBeliefs``)."""
        beliefs = beliefs_of(planner)
        if beliefs is not None:
            self.cell_km = float(beliefs.cfg.cell_km)
            beliefs.observers.append(self.record)
        return self

    @staticmethod
    def of(planner) -> PursuitLog | None:
        """The log attached to ``planner`` (also after a checkpoint restored it), or None."""
        beliefs = beliefs_of(planner)
        for observe in () if beliefs is None else beliefs.observers:
            owner = getattr(observe, "__self__", None)
            if isinstance(owner, PursuitLog):
                return owner
        return None

    def record(self, planner: SwarmBeliefs, decision) -> None:
        """The facts of the step just decided (``decision``: its ``StepDecision``) from the
        swarm's beliefs ``planner``; called before the forecast, so beliefs are those the step
        acted on."""
        step = int(planner.k)
        flying = np.flatnonzero(~np.asarray(planner.done, dtype=bool))
        if flying.size:
            rows, cells = self._candidates(planner, flying)
            p = planner.engage_probability(rows, cells) if len(rows) else np.zeros(0)
            high = p >= self.floor
            if high.any():
                grid = planner.grid
                keys = grid.flat(cells[high])
                order = np.lexsort((-p[high], keys))  # per cell, its highest belief first
                keys, values = keys[order], p[high][order]
                first = np.concatenate(([True], keys[1:] != keys[:-1]))
                xs, ys = np.unravel_index(keys[first], grid.shape)
                self.beliefs.extend(
                    [step, int(x), int(y), round(float(v), 4)]
                    for x, y, v in zip(xs.tolist(), ys.tolist(), values[first].tolist(),
                                       strict=True)
                )  # fmt: skip
        tracking = np.flatnonzero((planner.track[:, 0] >= 0) & ~np.asarray(planner.done))
        self.tracks.extend(
            [step, int(i), int(planner.track[i, 0]), int(planner.track[i, 1]),
             int(bool(planner.track_confirmed[i]))]
            for i in tracking.tolist()
        )  # fmt: skip
        self.engage_requests.extend(
            [step, int(i)] for i in np.flatnonzero(np.asarray(decision.engage)).tolist()
        )

    def _candidates(self, planner, flying: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(UAV, cell) pairs worth ``engage_probability``: each flying UAV's footprint cells and
        track cell, less those whose bound ``sum_e p_(c+e) * fraction_e`` (>= the probability,
        by the union bound) is under the floor. One read of the UAV's existence probabilities
        on the square around it serves the bound of every footprint cell."""
        grid = planner.grid
        self._prepare(planner)
        around = planner.cells[flying][:, None, :] + self._square[None]  # (F, S, 2)
        window = planner.tpm.existence_at(flying[:, None], around)  # (F, S), 0 outside
        bound = (window[:, self._gather] * planner.engage_fractions).sum(axis=2)  # (F, K)
        uav, k = np.nonzero(bound >= self.floor)
        rows = flying[uav]
        cells = planner.cells[rows] + planner.footprint[k]
        track = planner.track[flying]
        tracked = grid.inside(track)
        rows = np.concatenate([rows, flying[tracked]])
        cells = np.concatenate([cells, track[tracked]]).reshape(-1, 2)
        inside = grid.inside(cells)
        return rows[inside], cells[inside]

    def _prepare(self, planner) -> None:
        """Set up, once, the square of cells around a UAV that holds every footprint cell's
        engage disc, and where each (footprint cell, disc cell) pair sits in it."""
        if getattr(self, "_square", None) is None:
            reach = int(np.abs(planner.footprint).max() + np.abs(planner.engage_cells).max())
            side = 2 * reach + 1
            span = np.arange(-reach, reach + 1)
            self._square = np.stack(np.meshgrid(span, span, indexing="ij"), -1).reshape(-1, 2)
            pos = planner.footprint[:, None, :] + planner.engage_cells[None] + reach  # (K, E, 2)
            self._gather = pos[..., 0] * side + pos[..., 1]

    def facts(self) -> dict:
        """The log as JSON-ready lists (the ``planner_facts`` of a result)."""
        return {
            "cell_km": self.cell_km,
            "belief_floor": self.floor,
            "beliefs": [list(b) for b in self.beliefs],
            "tracks": [list(t) for t in self.tracks],
            "engage_requests": [list(r) for r in self.engage_requests],
        }
