"""Knowing when the daemon cannot keep up with the vehicles' clock (issue 12, finding 3).

Paced time (``--time-scale X``: SITL ``--speedup``, or real aircraft at 1) gives the daemon
``step_s / X`` wall seconds per decision step, and the planes fly on meanwhile. At 50x on a
loaded machine the daemon fell behind, said so, and flew on: planes ~1 km inside a threat
circle. Two guards:

* **At start** (:func:`refuse_unkeepable_time_scale`), before any vehicle is touched: a short
  calibration runs the decision step's computation (planner, cell envelope, flight-path
  envelope) on the scenario for a few steps and measures its wall time on this machine, now.
  A time scale whose decision period, times the share a step may use
  (``pacing.STEP_DEADLINE_SHARE``), is shorter than ``CALIBRATION_HEADROOM`` times that is
  refused in one line naming the largest time scale that fits, and lockstep.
* **In flight** (:class:`HoldWhenLate`): each step's lateness, as the pacing measures it on the
  vehicles' own clock as the step's commands are about to go out (``pacing.Lateness``): how far
  the vehicles had flown past the step's decision instant, or how far this decision instant is
  past one period after the last one (a stall: a whole decision passed without one). Beyond
  ``bound_s`` (one decision period by default) the step's new targets are not sent: every
  plane keeps flying to, and circling, the last guided target it accepted, which the flight
  envelope proved clear of every threat, loiter circle included. The daemon says so once per
  episode, and again when it has caught up; held steps are counted (``held_steps``). Held
  planes whose circles would come within d_min of each other are moved apart
  (:func:`held_apart`).
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mavlink_bridge.mission.pacing import STEP_DEADLINE_SHARE
from mavlink_bridge.safety.flight_envelope import FlightEnvelope
from mavlink_bridge.safety.safety_envelope import SafetyEnvelope
from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_bridge.way_home.kept_apart import ReturnSeparation
from planner.errors import UserError
from planner.grid import Grid
from planner.scenario import Scenario

#: the measured computation must fit this many times into a step's share of the period: the
#: machine's load changes, and sending and acknowledging commands take their time too
CALIBRATION_HEADROOM = 2.0
CALIBRATION_STEPS = 4


def measure_step_wall_s(
    scenario: Scenario,
    seed: int,
    planner_cls: type,
    cells_envelope: SafetyEnvelope,
    flight_envelope: FlightEnvelope | None,
    steps: int = CALIBRATION_STEPS,
) -> float:
    """Wall seconds one decision step's computation takes here and now: the planner, the
    cell-level and the flight-path envelope on the scenario's own start, flown ``steps`` steps
    as if every plane reached its cell (median of the steps after the first, which warms up)."""
    cfg = scenario.config
    grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
    starts = scenario.starts_for_seed(seed)
    planner = planner_cls(scenario, starts, seed)
    n = len(starts)
    xy = np.array([[s.x_km, s.y_km] for s in starts], float)
    cells = grid.cell_of(xy)
    home = grid.centre_km(cells)
    headings = np.array([int(round(s.heading_deg / 45.0)) % 8 for s in starts])
    active = np.ones(n, dtype=bool)
    flown = np.zeros(n)
    aims = np.full((n, 2), np.nan)
    times = []
    for _ in range(max(2, steps)):
        started = time.perf_counter()
        decision = planner.step(cells.copy(), headings.copy(), [None] * n, [None] * n, active)
        checked = cells_envelope.check(
            cells, headings, np.asarray(decision.next_cells), np.asarray(decision.next_headings),
            flown, home, active,
        )  # fmt: skip
        next_cells, next_headings = checked.next_cells, checked.next_headings
        if flight_envelope is not None:
            positions = grid.centre_km(cells)
            choice = flight_envelope.choose(
                positions, headings * math.pi / 4, np.full(n, cfg.speed_mps), cells, headings,
                next_cells, next_headings, aims, flown, home, active, 1.0,
            )  # fmt: skip
            aims = choice.aims_km
            next_cells, next_headings = choice.next_cells, choice.next_headings
        times.append(time.perf_counter() - started)
        flown += np.hypot(*(grid.centre_km(next_cells) - grid.centre_km(cells)).T)
        cells, headings = np.asarray(next_cells), np.asarray(next_headings)
    return float(statistics.median(times[1:]))


def keepable_time_scale(step_wall_s: float, step_s: float) -> float:
    """The largest time scale whose decision period leaves the step its share with headroom."""
    return STEP_DEADLINE_SHARE * step_s / (CALIBRATION_HEADROOM * max(step_wall_s, 1e-6))


def refuse_unkeepable_time_scale(time_scale: float, step_s: float, step_wall_s: float) -> None:
    """One line, before any vehicle is touched, when ``time_scale`` cannot be kept."""
    best = keepable_time_scale(step_wall_s, step_s)
    if time_scale <= best:
        return
    period = step_s / time_scale
    fits = math.floor(best) if best >= 1 else round(best, 2)
    raise UserError(
        f"--time-scale {time_scale:g} leaves {period * 1e3:.0f} ms of wall time per "
        f"{step_s:g} s decision step, and a step's computation takes {step_wall_s * 1e3:.0f} ms "
        f"on this machine now (measured over {CALIBRATION_STEPS} steps; {CALIBRATION_HEADROOM:g}x"
        f" headroom needed): run the vehicles at --time-scale {fits:g} or less, or use lockstep "
        f"(swarmplan sim --lockstep, swarmplan daemon --lockstep)"
    )


@dataclass
class HoldWhenLate:
    """Paced time: hold the planes at their last safe targets while the daemon is late (by the
    pacing's measure of each step's lateness: ``pacing.Lateness``)."""

    bound_s: float  # vehicle seconds of lateness beyond which a step holds
    say: Callable[[str], None] = lambda text: None
    held_steps: int = 0
    holding: bool = False
    max_lateness_s: float = 0.0

    def hold(self, step: int, late_s: float) -> bool:
        """Should this step, ``late_s`` of the vehicles' seconds late, hold (send nothing
        new)? Says when a hold starts and ends."""
        self.max_lateness_s = max(self.max_lateness_s, late_s)
        if late_s > self.bound_s:
            self.held_steps += 1
            if not self.holding:
                self.say(
                    f"warning: holding at step {step}: the step is {late_s:.1f} s late on the "
                    f"vehicles' clock (bound {self.bound_s:g} s); every plane circles the last "
                    f"target it accepted (clear of every threat) until the daemon catches up; "
                    f"lower the vehicles' speedup (--time-scale) or use lockstep"
                )
            self.holding = True
            return True
        if self.holding:
            self.say(f"caught up at step {step} ({late_s:.1f} s behind): flying the plan again")
        self.holding = False
        return False


def held_apart(
    separation: ReturnSeparation, planes: list[tuple[VehicleKey, np.ndarray, float, np.ndarray]]
) -> tuple[dict[VehicleKey, np.ndarray], list[VehicleKey]]:
    """While the daemon holds, every plane (system id, where, course, its last target) circles
    its last target, each proven clear of every threat but not of each other: the targets were
    chosen a step apart, for a step, and a hold may last many (held planes 0.26-0.76 km apart
    at 30 % loss and 20x on a loaded machine). Judged as the plane model flies them, there and
    round the circle (``ReturnSeparation.guided_flights``), planes already on their circles
    first: a plane whose flight comes within d_min of one kept is moved to the nearest point
    whose circle keeps the threat margin and whose way there conflicts with none kept
    (``ReturnSeparation.hold``). Returns the moves (system id -> point) and the planes
    no point clears (left where they are)."""
    flights = []
    for sid, xy, course, target in planes:
        (flight,) = separation.guided_flights(sid, xy, course, np.asarray(target, float)[None])
        flights.append((flight, course))
    kept: list = []
    moves: dict[VehicleKey, np.ndarray] = {}
    stuck: list[VehicleKey] = []
    for flight, course in sorted(flights, key=lambda fc: (fc[0].arrival_s, fc[0].key)):
        if not separation.conflicts(flight, kept):
            kept.append(flight)
            continue
        found = separation.hold(flight, course, kept)
        if found is None:
            stuck.append(flight.key)
            kept.append(flight)
            continue
        moves[flight.key], moved = found
        kept.append(moved)
    return moves, stuck
