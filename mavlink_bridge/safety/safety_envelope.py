"""The safety envelope: every guided target is checked here, independently of the planner,
before it is sent to a vehicle.

A proposed move (current cell -> next cell) is safe when

* the next cell lies inside the mission area;
* the straight leg between the two cell centres keeps ``threat_margin_km`` clear of every
  threat circle (the operator's threat list, all of it, known or not to the planner);
* the next cell centre is at least ``min_separation_km + separation_margin_km`` from every other
  active UAV's next cell (the margin absorbs how far telemetry positions lag the cells);
* the distance flown so far, plus the leg, plus the straight line home stays within
  ``max_range_km`` (constraint C_r).

An unsafe move is replaced by the safe move closest to it among the turns the airframe can make
in one step (``max_turn_deg``), first among those that land where a turn-limited path goes on
safely for ever (``viable``: not a row along the area's edge heading out of it, nor a pocket
against a threat, judged with this envelope's threats and margin); if none is safe, by the
reachable cell farthest from the threats (holding, i.e. circling, only when no move is better).
Every replacement is reported with its reason. A UAV with no safe move at all is settled
first, so the others keep apart from where it holds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from planner.constraints import SafetyModel, segment_clearance
from planner.grid import HEADING_STEPS, Grid, turn_options
from planner.scenario import Scenario


@dataclass(frozen=True)
class Override:
    """A move the envelope replaced."""

    uav: int
    reason: str  # "area", "threat", "separation" or "range"
    proposed: tuple[int, int]
    chosen: tuple[int, int]


@dataclass
class EnvelopeDecision:
    """The checked next cells and headings, and what was changed."""

    next_cells: np.ndarray
    next_headings: np.ndarray
    overrides: list[Override] = field(default_factory=list)


@dataclass(frozen=True)
class SafetyEnvelope:
    """Limits every guided target must respect."""

    grid: Grid
    threat_xy_km: np.ndarray  # (M, 2)
    threat_radius_km: np.ndarray  # (M,)
    threat_margin_km: float = 1.0
    min_separation_km: float = 1.0
    separation_margin_km: float = 1.0
    max_range_km: float = math.inf
    max_turn_deg: float = 45.0

    @classmethod
    def for_scenario(
        cls, scenario: Scenario, threat_margin_km: float = 1.0, separation_margin_km: float = 1.0
    ) -> SafetyEnvelope:
        cfg = scenario.config
        return cls(
            grid=Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km),
            threat_xy_km=np.array([[t.x_km, t.y_km] for t in scenario.threats], float).reshape(
                -1, 2
            ),
            threat_radius_km=np.array([t.radius_km for t in scenario.threats], float),
            threat_margin_km=threat_margin_km,
            min_separation_km=cfg.min_separation_km,
            separation_margin_km=separation_margin_km,
            max_range_km=cfg.max_range_km,
            max_turn_deg=cfg.max_turn_deg,
        )

    @cached_property
    def _kernel(self) -> SafetyModel:
        return SafetyModel(
            self.grid, self.threat_xy_km, self.threat_radius_km, self.threat_margin_km,
            self.max_turn_deg,
        )  # fmt: skip

    def viable(self, cell: np.ndarray, heading: int) -> bool:
        """Arrived at ``cell`` with ``heading``, some turn-limited path stays in the area and
        ``threat_margin_km`` clear of every threat for ever (the planner's viability kernel,
        planner/constraints.py, over this envelope's threats and margin)."""
        return bool(self.grid.inside(cell)) and bool(self._kernel.viable[heading, cell[0], cell[1]])

    # ------------------------------------------------------------------ single rules

    def segment_clear(self, a: np.ndarray, b: np.ndarray) -> bool:
        """The segment ``a``-``b`` (km) keeps ``threat_margin_km`` clear of every threat."""
        clearance = segment_clearance(a, b, self.threat_xy_km, self.threat_radius_km)
        return bool(clearance >= self.threat_margin_km)

    def leg_clear_of_threats(self, cell_from: np.ndarray, cell_to: np.ndarray) -> bool:
        return self.segment_clear(self.grid.centre_km(cell_from), self.grid.centre_km(cell_to))

    def within_range(
        self, cell_from: np.ndarray, cell_to: np.ndarray, flown_km: float, home_km: np.ndarray
    ) -> bool:
        if not math.isfinite(self.max_range_km):
            return True
        a, b = self.grid.centre_km(cell_from), self.grid.centre_km(cell_to)
        leg = float(np.hypot(*(b - a)))
        home = float(np.hypot(*(home_km - b)))
        # staying put (or moving closer to home) is never refused for range: it only helps
        if leg == 0 or home + leg <= float(np.hypot(*(home_km - a))) + 1e-9:
            return True
        return flown_km + leg + home <= self.max_range_km + 1e-9

    def static_reason(
        self, cell_from: np.ndarray, cell_to: np.ndarray, flown_km: float, home_km: np.ndarray
    ) -> str | None:
        """The first rule (other than separation) a move breaks, or None."""
        if not bool(self.grid.inside(cell_to)):
            return "area"
        if not self.leg_clear_of_threats(cell_from, cell_to):
            return "threat"
        if not self.within_range(cell_from, cell_to, flown_km, home_km):
            return "range"
        return None

    def separated(self, cell: np.ndarray, others: np.ndarray) -> bool:
        if len(others) == 0:
            return True
        d = np.hypot(*(self.grid.centre_km(others) - self.grid.centre_km(cell)).T)
        return bool(np.all(d >= self.min_separation_km + self.separation_margin_km - 1e-9))

    # ------------------------------------------------------------------ the whole swarm

    def check(
        self,
        cells: np.ndarray,
        headings: np.ndarray,
        next_cells: np.ndarray,
        next_headings: np.ndarray,
        flown_km: np.ndarray,
        home_km: np.ndarray,
        active: np.ndarray,
    ) -> EnvelopeDecision:
        """Check (and where needed replace) the proposed moves of every active UAV."""
        cells = np.asarray(cells, dtype=np.int64)
        out_cells = np.array(next_cells, dtype=np.int64, copy=True)
        out_headings = np.array(next_headings, dtype=np.int64, copy=True)
        overrides: list[Override] = []
        flying = [i for i in range(len(cells)) if active[i]]
        reasons = {
            i: self.static_reason(cells[i], out_cells[i], float(flown_km[i]), home_km[i])
            for i in flying
        }
        # a UAV with no safe move holds (or escapes) wherever the others go: it settles first,
        # so the others keep apart from it (settled after them, a plane held in a corner let
        # another fly its next cell 0.4 km from it)
        cornered = {
            i for i in flying
            if reasons[i] is not None
            and not self._has_safe_move(cells[i], int(headings[i]), flown_km[i], home_km[i])
        }  # fmt: skip
        settled: list[int] = []
        for i in sorted(flying, key=lambda i: i not in cornered):
            others = out_cells[settled] if settled else np.empty((0, 2), np.int64)
            proposed = out_cells[i].copy()
            reason = reasons[i]
            if reason is None and not self.separated(proposed, others):
                reason = "separation"
            if reason is not None:
                cell, heading = self._alternative(
                    cells[i], int(headings[i]), proposed, float(flown_km[i]), home_km[i], others
                )
                out_cells[i], out_headings[i] = cell, heading
                overrides.append(
                    Override(
                        i,
                        reason,
                        (int(proposed[0]), int(proposed[1])),
                        (int(cell[0]), int(cell[1])),
                    )
                )
            settled.append(i)
        return EnvelopeDecision(out_cells, out_headings, overrides)

    def _has_safe_move(
        self, cell: np.ndarray, heading: int, flown_km: float, home_km: np.ndarray
    ) -> bool:
        """Some move within the turn limit breaks none of the rules but separation."""
        return any(
            self.static_reason(cell, cell + HEADING_STEPS[int((heading + turn) % 8)],
                               float(flown_km), home_km) is None
            for turn in turn_options(self.max_turn_deg)
        )  # fmt: skip

    def _alternative(
        self,
        cell: np.ndarray,
        heading: int,
        proposed: np.ndarray,
        flown_km: float,
        home_km: np.ndarray,
        others: np.ndarray,
    ) -> tuple[np.ndarray, int]:
        """The safe reachable cell nearest the proposed one, a viable one first (a safe cell on
        the area's edge heading out of it leaves only holds next), else the current cell
        (hold)."""
        best: tuple[tuple[bool, float], np.ndarray, int] | None = None
        for turn in turn_options(self.max_turn_deg):
            h = int((heading + turn) % 8)
            candidate = cell + HEADING_STEPS[h]
            if self.static_reason(cell, candidate, flown_km, home_km) is not None:
                continue
            if not self.separated(candidate, others):
                continue
            rank = (not self.viable(candidate, h), float(np.hypot(*(candidate - proposed))))
            if best is None or rank < best[0]:
                best = (rank, candidate, h)
        if best is not None:
            return best[1], best[2]
        return self._escape(cell, heading)

    def aim_point_km(
        self, cell_from: np.ndarray, cell_to: np.ndarray, lead: float = 1.0
    ) -> np.ndarray:
        """Where to send the plane for a move: the next cell's centre extended ``lead`` legs
        further along the move (a carrot: the plane flies through the centre without arriving and
        circling), shortened until the extension stays in the area and clear of the threats."""
        a, b = self.grid.centre_km(cell_from), self.grid.centre_km(cell_to)
        for c, r in zip(self.threat_xy_km, self.threat_radius_km, strict=True):
            away = b - c
            distance = float(np.hypot(*away))
            if distance < r + self.threat_margin_km:  # an escape cell: aim clear of the zone
                direction = (
                    away / distance
                    if distance > 1e-9
                    else (a - c) / max(float(np.hypot(*(a - c))), 1e-9)
                )
                return c + direction * (r + self.threat_margin_km)
        leg = b - a
        if not np.any(leg):
            return b
        width, height = self.grid.nx * self.grid.cell_km, self.grid.ny * self.grid.cell_km
        for fraction in (lead, lead / 2, 0.0):
            aim = b + fraction * leg
            inside = 0 <= aim[0] <= width and 0 <= aim[1] <= height
            if inside and self.segment_clear(b, aim):
                return aim
        return b

    def threat_clearance(self, cell: np.ndarray) -> float:
        """Distance (km) from a cell centre to the nearest threat edge (negative inside)."""
        if len(self.threat_radius_km) == 0:
            return math.inf
        d = np.hypot(*(self.threat_xy_km - self.grid.centre_km(cell)).T) - self.threat_radius_km
        return float(d.min())

    def _escape(self, cell: np.ndarray, heading: int) -> tuple[np.ndarray, int]:
        """No safe move: take the reachable in-area cell with the most clearance from the threats
        (a plane cannot stop: told to hold, it circles at its minimum turn radius, ~1 km at
        100 m/s, so holding near a threat is worse than moving away); hold only if nothing is
        better."""
        best = (self.threat_clearance(cell) - 1e-6, cell.copy(), heading)
        for turn in turn_options(self.max_turn_deg):
            h = int((heading + turn) % 8)
            candidate = cell + HEADING_STEPS[h]
            if not bool(self.grid.inside(candidate)):
                continue
            clearance = self.threat_clearance(candidate)
            if clearance > best[0]:
                best = (clearance, candidate, h)
        return best[1], best[2]
