"""What the decision loop carries from one step to the next (:class:`LoopState`: what a
checkpoint holds, ``checkpoint.LOOP_STATE``), and a plane's heading from its course."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from mavlink_bridge.vehicles.vehicle_state import VehicleState
from planner.engagement import EngagementOutcome
from planner.grid import Grid, heading_of_angle
from planner.scenario import UavStart


def course_heading(v: VehicleState) -> int | None:
    """Heading index of the vehicle's velocity (or compass heading), None if unknown."""
    if v.speed_mps > 1.0:
        return int(heading_of_angle(v.course_rad))
    if v.heading_cdeg != 65535:
        compass = v.heading_cdeg / 100.0
        return int(heading_of_angle(math.radians(90.0 - compass)))
    return None


@dataclass
class LoopState:
    """What the decision loop carries from one step to the next (every field but
    ``positions_ms`` is in a checkpoint, by name: ``checkpoint.LOOP_STATE``)."""

    planner: Any
    recorder: Any
    starts: tuple[UavStart, ...]
    home_km: np.ndarray
    cells: np.ndarray
    headings: np.ndarray
    commanded_cells: np.ndarray
    commanded_headings: np.ndarray
    last_target: list[tuple[float, float] | None]
    consumed: list[int]  # index of the last look each UAV's step used
    flown_km: np.ndarray  # between measured cells, as the planner counts
    engagements: list[EngagementOutcome | None]  # outcomes to give the planner next step
    engage_seq: list[int]
    pending_engage: list[int]  # sequence number of an unanswered engagement, asked again
    refusals: list[int]  # consecutive refused guided targets
    observed: np.ndarray
    engaged_ids: set[int]
    engaged_value: float
    positions: np.ndarray  # (N, 2) km at the decision instant
    previous_centres: np.ndarray
    positions_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))  # vehicle clock there

    def last_targets_km(self) -> np.ndarray:
        """(N, 2) the guided target each plane last accepted (NaN: none yet)."""
        return np.array([t if t is not None else (np.nan, np.nan) for t in self.last_target])

    @classmethod
    def start(
        cls,
        grid: Grid,
        planner: Any,
        recorder: Any,
        starts: tuple[UavStart, ...],
        consumed: list[int],
    ) -> LoopState:
        n = len(starts)
        home_km = np.array([[s.x_km, s.y_km] for s in starts])
        cells = grid.cell_of(home_km)
        headings = np.array([int(heading_of_angle(math.radians(s.heading_deg))) for s in starts])
        positions = grid.centre_km(cells)
        return cls(
            planner=planner,
            recorder=recorder,
            starts=starts,
            home_km=home_km,
            cells=cells,
            headings=headings,
            commanded_cells=cells.copy(),
            commanded_headings=headings.copy(),
            last_target=[None] * n,
            consumed=list(consumed),
            flown_km=np.zeros(n),
            engagements=[None] * n,
            engage_seq=[0] * n,
            pending_engage=[0] * n,
            refusals=[0] * n,
            observed=np.zeros(grid.shape, dtype=bool),
            engaged_ids=set(),
            engaged_value=0.0,
            positions=positions,
            previous_centres=positions.copy(),
            positions_ms=np.zeros(n),
        )

    @classmethod
    def from_checkpoint(cls, loop: dict[str, Any]) -> LoopState:
        state = cls(**{f.name: loop[f.name] for f in fields(cls) if f.name in loop})
        state.positions_ms = np.zeros(len(state.starts))
        return state

    def checkpoint_view(self) -> dict[str, Any]:
        """The fields a checkpoint holds, by name."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "positions_ms"}
