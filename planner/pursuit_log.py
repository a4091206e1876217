"""What the planner believed and did about targets, step by step: the planner's half of the
per-target account (``sim_gateway.target_account`` holds the ground-truth half and joins them).

The log reads the planner's state, never writes it, and never sees ground truth: it records, at
each decision step after the planner decided and before it forecast its beliefs (eqs 19-22):

- **belief peaks**: the probability that a target lies within the engage radius of a cell
  (``HapfAcoPlanner.engage_probability``, section 3.2.1, from the TPM of eqs 16-18), at the
  cells of each flying UAV's own sensor footprint and at the cell it pursues, as that UAV
  believes it; a cell's entry is the highest over the UAVs and is kept when it reaches
  ``floor`` (a target never looked at keeps its prior, far below it);
- **pursuits**: the cell each UAV goes for (``HapfAcoPlanner.track``) and whether its target
  counts as confirmed there (``track_confirmed``);
- **engagement requests**: which UAVs asked for an engagement at that step.

Cells are grid indices; the join places them with the grid's cell size. Attach with
``PursuitLog.attach(planner)``: the planner calls ``record`` from its step (its ``observers``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

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
        """Record every step of ``planner`` (a ``HapfAcoPlanner`` or subclass) from now on."""
        self.cell_km = float(planner.cfg.cell_km)
        planner.observers.append(self.record)
        return self

    @staticmethod
    def of(planner) -> PursuitLog | None:
        """The log attached to ``planner`` (also after a checkpoint restored it), or None."""
        for observe in getattr(planner, "observers", ()):
            owner = getattr(observe, "__self__", None)
            if isinstance(owner, PursuitLog):
                return owner
        return None

    def record(self, planner, decision) -> None:
        """The facts of the step ``planner`` just decided (``decision``: its ``StepDecision``);
        called by the planner before its forecast, so beliefs are those the step acted on."""
        step = int(planner.k)
        flying = np.flatnonzero(~np.asarray(planner.done, dtype=bool))
        if flying.size:
            grid = planner.grid
            cells = planner.cells[flying][:, None, :] + planner.footprint[None]  # (F, K, 2)
            track = planner.track[flying]
            cells = np.concatenate([cells, track[:, None, :]], axis=1)  # own track cell last
            rows = np.repeat(flying, cells.shape[1])
            flat_cells = cells.reshape(-1, 2)
            keep = grid.inside(flat_cells)
            rows, flat_cells = rows[keep], flat_cells[keep]
            p = planner.engage_probability(rows, flat_cells)
            high = p >= self.floor
            if high.any():
                keys = grid.flat(flat_cells[high])
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

    def facts(self) -> dict:
        """The log as JSON-ready lists (the ``planner_facts`` of a result)."""
        return {
            "cell_km": self.cell_km,
            "belief_floor": self.floor,
            "beliefs": [list(b) for b in self.beliefs],
            "tracks": [list(t) for t in self.tracks],
            "engage_requests": [list(r) for r in self.engage_requests],
        }
