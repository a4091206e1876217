"""Step views from the two kinds of mission: an offline run (``sim_gateway.offline_runner``'s
``OfflineStep``) and a MAVLink mission (the daemon's per-step record). Read by duck typing: this
package imports neither ``sim_gateway`` nor ``mavlink_bridge``."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mission_view.view_model import StepView, TimelineEvent, VehicleView
from planner.grid import Grid
from planner.planner_interface import MODES
from planner.scenario import Scenario


def _mode_name(decision: Any, i: int) -> str:
    modes = getattr(decision, "modes", None)
    if modes is None:
        return ""
    m = int(modes[i])
    return MODES[m] if 0 <= m < len(MODES) else str(m)


class OfflineViews:
    """``OfflineStep`` -> ``StepView``; keeps the engaged totals."""

    def __init__(self, scenario: Scenario) -> None:
        cfg = scenario.config
        self.grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
        self.engaged = 0
        self.engaged_value = 0.0
        self.homes: list[tuple[float, float]] | None = None  # the starts (first record)

    def view(self, record: Any) -> StepView:
        k, decision = record.step, record.decision
        positions = np.asarray(record.positions_km, dtype=float)
        if self.homes is None:
            self.homes = [(float(x), float(y)) for x, y in positions.tolist()]
        events = []
        for i, outcome in record.engagements:
            x, y = (float(c) for c in positions[i])
            if outcome.success:
                self.engaged += 1
                self.engaged_value += outcome.value
                text = f"engaged target {outcome.target_id} (value {outcome.value:g})"
                events.append(TimelineEvent(k, "engagement", text, i, x, y))
            else:
                events.append(TimelineEvent(k, "miss", "engagement: no target in reach", i, x, y))
        targets = None if decision is None else self.grid.centre_km(decision.next_cells)
        vehicles = []
        for i, (x, y) in enumerate(positions.tolist()):
            done = decision is not None and bool(decision.done[i])
            target = (
                None if targets is None or done else (float(targets[i, 0]), float(targets[i, 1]))
            )
            vehicles.append(
                VehicleView(
                    x,
                    y,
                    float(record.headings[i]) * 45.0,
                    active=True,
                    target_km=target,
                    mode="grid",
                    planner_mode=_mode_name(decision, i),
                    ground_speed_mps=None,
                    done=done,
                    home_km=self.homes[i],
                )  # fmt: skip
            )
        truth = [[int(t[0]), round(float(t[1]), 3), round(float(t[2]), 3), int(t[3])]
                 for t in np.asarray(record.truth).tolist()]  # fmt: skip
        return StepView(
            k, vehicles, coverage=float(record.coverage), engaged=self.engaged,
            engaged_value=self.engaged_value, truth=truth, events=events,
        )  # fmt: skip


def course_deg(vn_mps: float, ve_mps: float, fallback_deg: float) -> float:
    """Course over ground, counter-clockwise from east (degrees), or ``fallback_deg`` at rest."""
    if math.hypot(vn_mps, ve_mps) > 1.0:
        return math.degrees(math.atan2(vn_mps, ve_mps))
    return fallback_deg
