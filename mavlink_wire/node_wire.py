"""The planner's swarm messages (``planner.swarm_messages``) on the swarm link
(``mavlink_wire.swarm_wire``, docs/onboard.md "The swarm link"): what one node sends in one
exchange of a decision step becomes one :class:`~mavlink_wire.swarm_wire.SwarmReport`, and a
report heard becomes the planner's messages again.

- exchange 1 (``UavNode.begin``): ``UavState``, ``Engagements``, ``ThreatsFound`` and the
  ``Look`` -> the report's state (flying in the heading byte), engagement outcome, serviced
  targets with their cells, threats (sent as the scenario's circles, heard back as indices) and
  look (its centre cell and one bit per footprint cell in ``Grid.disc_offsets`` order);
- exchange 2 (``UavNode.hear``): ``TrackIntent`` -> the report's intent;
- claims (``UavNode.claim`` / ``answer`` / ``hold_claim``): ``CellClaim`` -> a move claim with
  its ordered alternatives and its request to step aside.

A report with a state decodes to the four messages of exchange 1 (the engagements and threats
even when empty, as ``begin`` sends them). Positions travel in whole metres (receivers plan with
cells, never with the measured position), the course in 1/100 degree and the ground speed in
cm/s (the neighbours' flight envelopes predict its flight from them); everything else comes back
exactly.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mavlink_wire.swarm_wire import (
    NO_CELL_WIRE,
    Engagement,
    Intent,
    MoveClaim,
    NodeState,
    SwarmReport,
    ThreatReport,
    WireError,
)
from mavlink_wire.swarm_wire import Look as WireLook
from planner.grid import Grid
from planner.scenario import Scenario
from planner.swarm_messages import (
    NO_CELL,
    CellClaim,
    Engagements,
    Look,
    Message,
    ThreatsFound,
    TrackIntent,
    UavState,
)

#: a threat heard is the scenario's when its centre and radius agree within this (metres sent)
THREAT_MATCH_KM = 0.002


def _cell_out(cell: tuple[int, int]) -> tuple[int, int]:
    return NO_CELL_WIRE if tuple(cell) == NO_CELL else (int(cell[0]), int(cell[1]))


def _cell_in(cell: tuple[int, int]) -> tuple[int, int]:
    return NO_CELL if tuple(cell) == NO_CELL_WIRE else (int(cell[0]), int(cell[1]))


@dataclass(frozen=True)
class NodeWire:
    """The mapping for one scenario: its grid, the sensor's footprint and the threats."""

    grid: Grid
    offsets: np.ndarray  # (K, 2) the footprint around a look's centre, Grid.disc_offsets order
    threats: tuple[tuple[float, float, float], ...]  # (x, y, radius) km, the scenario's order

    @classmethod
    def for_scenario(cls, scenario: Scenario) -> NodeWire:
        cfg = scenario.config
        grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
        threats = tuple((t.x_km, t.y_km, t.radius_km) for t in scenario.threats)
        return cls(grid, grid.disc_offsets(cfg.detection_radius_km), threats)

    # ------------------------------------------------------------------ to the wire

    def report(self, uav: int, step: int, messages: Sequence[Message]) -> SwarmReport:
        """One report of ``messages`` (one node's, of one exchange of step ``step``)."""
        parts: dict = {"looks": [], "moves": []}
        for m in messages:
            if isinstance(m, UavState):
                parts["state"] = NodeState(m.cell, m.heading, m.position_km[0],
                                           m.position_km[1], m.radius_km, m.flying,
                                           m.course_rad, m.speed_mps)  # fmt: skip
            elif isinstance(m, Look):
                parts["looks"].append(self._look_out(m))
            elif isinstance(m, Engagements):
                if m.outcome is not None:
                    target, success, cell = m.outcome
                    parts["engagements"] = (Engagement(target, cell, step, bool(success)),)
                parts["serviced_at"] = tuple((t, tuple(c)) for t, c in m.serviced)
            elif isinstance(m, ThreatsFound):
                parts["threats"] = tuple(ThreatReport(*self.threats[t]) for t in m.threats)
            elif isinstance(m, TrackIntent):
                parts["intent"] = Intent(_cell_out(m.track), m.priority)
            elif isinstance(m, CellClaim):
                displace = None if m.displace is None else (m.displace[0], m.displace[1])
                parts["moves"].append(MoveClaim(m.cell, m.heading, m.alternatives, displace))
        parts["looks"], parts["moves"] = tuple(parts["looks"]), tuple(parts["moves"])
        return SwarmReport(uav, step, **parts)

    def _look_out(self, look: Look) -> WireLook:
        cells = np.array(look.cells, dtype=np.int64).reshape(-1, 2)
        centre = self.look_centre(cells)
        seen = {tuple(c): d for c, d in zip(look.cells, look.detected, strict=True)}
        bits = tuple(bool(seen.get((int(x), int(y)), False)) for x, y in centre + self.offsets)
        return WireLook(look.uav, look.step, (int(centre[0]), int(centre[1])), bits)

    def look_centre(self, cells: np.ndarray) -> np.ndarray:
        """The centre cell whose footprint, cut to the area, is ``cells`` (in its order)."""
        for offset in self.offsets:
            centre = cells[0] - offset
            disc = centre + self.offsets
            disc = disc[self.grid.inside(disc)]
            if disc.shape == cells.shape and (disc == cells).all():
                return centre
        raise WireError(f"a look's {len(cells)} cells are not one footprint of the scenario")

    # ------------------------------------------------------------------ from the wire

    def messages(self, report: SwarmReport) -> list[Message]:
        """The planner's messages in a report heard (exchange 1's four when it has a state)."""
        uav, k, out = report.uav, report.step, []
        s = report.state
        if s is not None:
            out.append(UavState(uav, k, s.cell, s.heading, (s.x_km, s.y_km), s.coop_radius_km,
                                s.flying, s.course_rad, s.speed_mps))  # fmt: skip
            e = report.engagements[0] if report.engagements else None
            outcome = None if e is None else (e.target_id, int(e.success), e.cell)
            out.append(Engagements(uav, k, outcome, tuple(report.serviced_at)))
            out.append(ThreatsFound(uav, k, tuple(self._threat_index(t) for t in report.threats)))
        out.extend(self._look_in(look) for look in report.looks)
        if report.intent is not None:
            out.append(TrackIntent(uav, k, _cell_in(report.intent.track), report.intent.priority))
        for m in report.moves:
            out.append(CellClaim(uav, k, m.cell, m.heading, m.alternatives, m.displace))
        return out

    def _look_in(self, look: WireLook) -> Look:
        if len(look.detected) != len(self.offsets):
            raise WireError(f"a look of {len(look.detected)} footprint bits, the scenario's "
                            f"footprint has {len(self.offsets)}")  # fmt: skip
        cells = np.array(look.cell, dtype=np.int64) + self.offsets
        keep = self.grid.inside(cells)
        detected = np.array(look.detected, dtype=bool)[keep]
        return Look(look.uav, look.step, tuple((int(x), int(y)) for x, y in cells[keep]),
                    tuple(bool(d) for d in detected))  # fmt: skip

    def _threat_index(self, threat: ThreatReport) -> int:
        for t, (x, y, r) in enumerate(self.threats):
            if max(abs(x - threat.x_km), abs(y - threat.y_km), abs(r - threat.radius_km)) <= (
                THREAT_MATCH_KM
            ):
                return t
        raise WireError(f"a threat at ({threat.x_km}, {threat.y_km}) km is none of the scenario's")
