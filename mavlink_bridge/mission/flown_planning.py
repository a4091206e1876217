"""The scenario as the daemon's planner plans it: the paper's grid plus what a flown plane needs.

A plane does not fly cell centres. It turns on a circle of about 1 km at 100 m/s, lags after
turns, and circles the last target it was sent when no newer one comes. So the daemon's
planner plans with margins the paper's grid UAVs do not need (docs/daemon.md, "What the
planner plans with"):

* **separation**: ``min_separation_km`` plus ``separation_margin_km`` (the planes stray from
  the cells: two loiter circles and the predicted margin, at most 1 km,
  ``airframe.separation_margin_km``), and the UAVs within that plus ``CLOSING_CELLS`` always
  seen: two UAVs close by at most two diagonal cells in a step, so one seen any later can be
  met head-on with no
  separated move left (paper-10uav seed 11 planned as flown, sensing 3 km with d_min 2 km: two
  UAVs in one cell at step 224; 25 breaches of the planned 2 km in seeds 1-30, 3 with 4.83 km
  sensed, none of the scenario's 1 km);
* **threats**: every move, and the way home, at least the flight envelope's clearance of a
  guided target from the threat circles (``flight_margin_km``: the loiter circle as flown,
  judged out to a loiter diameter, plus the predicted margin; 2.39 km for the simulator's
  100 m/s plane, 0.41 km for ArduPlane's defaults). Planned at the paper's 0 km, the flight
  envelope replaced 150 of the planner's cells a mission (paper-10uav demo seed 1) and the
  planner's picture of where its UAVs were went wrong after each;
* **home**: a few steps more kept back for the way home (``home_reserve_extra_steps``).

``swarmplan run --as-flown`` (swarmplan/as_flown.py) plans the same scenario from the same plain
inputs (a daemon's default options, the airframe the simulator reports: no daemon): the offline
run a flown one is measured against (benchmarks/bench_end_to_end.py). The recorder of either
judges the scenario's own limits.
"""

from __future__ import annotations

import math
from dataclasses import replace

from mavlink_bridge.vehicles.flight_prediction import PlaneModel
from planner.scenario import Scenario

#: the most two UAVs close in one decision step, in cells: a diagonal move each, head-on
CLOSING_CELLS = 2 * math.sqrt(2)


def flight_margin_km(
    cell_margin_km: float, model: PlaneModel | None, predicted_margin_km: float
) -> float:
    """The clearance from the threat circles the flight envelope keeps for a guided target: its
    loiter circle at cruise, judged out to a loiter diameter (``loiter_reach_km``), plus the
    predicted margin; at least the cell-level envelope's margin. ``model`` None: no flight-path
    envelope, the cell-level margin alone."""
    if model is None:
        return cell_margin_km
    reach = float(model.loiter_reach_km(model.speed_mps))
    return max(cell_margin_km, reach + predicted_margin_km)


def planning_scenario(
    scenario: Scenario,
    steps: int,
    separation_margin_km: float,
    home_reserve_extra_steps: int,
    flight_margin: float,
) -> Scenario:
    """``scenario`` as the daemon's planner plans it for ``steps`` decision steps (its last
    step is the mission's: ``home_by_end`` plans to be home by then), with the separation
    margin on top of d_min, ``home_reserve_extra_steps`` more kept back for the way home, and
    the threat clearance ``flight_margin`` (km)."""
    cfg = scenario.config
    separation = cfg.min_separation_km + separation_margin_km
    planning = scenario.with_config(
        min_separation_km=separation,
        separation_sense_km=max(cfg.separation_sense_km, separation + CLOSING_CELLS * cfg.cell_km),
        threat_margin_km=max(cfg.threat_margin_km, flight_margin),
        home_path_margin_km=max(cfg.home_path_margin_km, flight_margin),
        home_reserve_steps=cfg.home_reserve_steps + home_reserve_extra_steps,
    )
    return replace(planning, steps=steps)
