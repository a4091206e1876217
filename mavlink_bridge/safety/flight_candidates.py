"""The guided targets the flight-path layer may send a plane, in the order they are tried.

``FlightEnvelope.choose`` (``flight_envelope.py``, whose docstring gives the order and why) sends
each plane the first of these whose predicted flight is safe. :class:`CandidateRows` lays every
active UAV's candidates out as the rows of one batch, with the airspeed each would be flown at.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavlink_bridge.safety.safety_envelope import SafetyEnvelope
from mavlink_bridge.vehicles.flight_prediction import PlaneModel, leg_speed_mps
from planner.grid import HEADING_STEPS, Grid, turn_options


@dataclass
class Candidate:
    """One guided target a plane may be sent: the cell and heading it stands for and the aim."""

    cell: np.ndarray
    heading: int
    aim: np.ndarray
    derived: bool = False  # cell/heading come from the predicted path (keep / circle)
    cruise: bool = False  # flown at cruise speed even with leg timing (a slower, tighter try)


def plane_candidates(
    env: SafetyEnvelope,
    leg_timing: bool,
    cell: np.ndarray,
    heading: int,
    proposed: np.ndarray,
    proposed_heading: int,
    previous_aim: np.ndarray,
    flown_km: float,
    home_km: np.ndarray,
    lead: float,
) -> list[Candidate]:
    """One plane's candidates, in the order they are tried (see the module docstring): a cell
    other than the planner's is offered only when the cell-level rules pass it."""
    first = Candidate(proposed, proposed_heading, env.aim_point_km(cell, proposed, lead))
    out = [first]
    if leg_timing:  # the planner's cell at cruise speed: a tighter turn and loiter
        out.append(Candidate(first.cell, first.heading, first.aim, cruise=True))
    others = []
    for turn in turn_options(env.max_turn_deg):
        h = int((heading + turn) % 8)
        c = cell + HEADING_STEPS[h]
        if np.array_equal(c, proposed) or env.static_reason(cell, c, flown_km, home_km):
            continue
        others.append((not env.viable(c, h), float(np.hypot(*(c - proposed))), h, c))
    for *_, h, c in sorted(others, key=lambda t: t[:2]):
        out.append(Candidate(c, h, env.aim_point_km(cell, c, lead)))
    if np.all(np.isfinite(previous_aim)):
        out.append(Candidate(cell, heading, np.asarray(previous_aim, float), derived=True))
    out.append(Candidate(cell, heading, env.grid.centre_km(cell), derived=True))
    return out


@dataclass
class CandidateRows:
    """Every UAV's candidates as rows (UAV i, candidate k) of one batch: the aim of each, where
    its plane starts, how fast it flies now and the airspeed it is to be sent for the leg."""

    candidates: list[list[Candidate]]  # per UAV, in the order they are tried; [] if inactive
    rows: list[tuple[int, int]]  # (UAV, candidate index), UAV by UAV
    aims_km: np.ndarray  # (M, 2)
    starts_km: np.ndarray  # (M, 2)
    speeds_now_mps: np.ndarray  # (M,)
    commanded_mps: np.ndarray  # (M,)

    @property
    def uav(self) -> np.ndarray:
        """(M,) the UAV of each row."""
        return np.array([i for i, _ in self.rows], dtype=np.int64)

    @property
    def row_of(self) -> dict[tuple[int, int], int]:
        """The row of each (UAV, candidate index)."""
        return {key: r for r, key in enumerate(self.rows)}


def candidate_rows(
    candidates: list[list[Candidate]],
    grid: Grid,
    model: PlaneModel,
    step_s: float,
    leg_timing: bool,
    cells: np.ndarray,
    positions_km: np.ndarray,
    speeds_mps: np.ndarray,
) -> CandidateRows:
    """The rows of ``candidates``, each to be flown at cruise speed or, with ``leg_timing``, at
    the airspeed that flies the leg from the plane's cell to the candidate's in one decision
    step (``flight_prediction.leg_speed_mps``; keep going and circle here: at cruise)."""
    rows = [(i, k) for i in range(len(candidates)) for k in range(len(candidates[i]))]
    aims = np.array([candidates[i][k].aim for i, k in rows]).reshape(-1, 2)
    starts = np.array([positions_km[i] for i, _ in rows]).reshape(-1, 2)
    speeds_now = np.array([speeds_mps[i] for i, _ in rows], dtype=float)
    commanded = np.full(len(rows), model.speed_mps)
    if leg_timing and rows:  # a cell's leg in one step; keep going / circle: cruise
        leg_from = grid.centre_km(np.array([cells[i] for i, _ in rows]))
        leg_to = grid.centre_km(np.array([candidates[i][k].cell for i, k in rows]))
        untimed = np.array([candidates[i][k].derived or candidates[i][k].cruise for i, k in rows])
        uavs = np.array([i for i, _ in rows])
        timed = leg_speed_mps(model, starts, leg_from, leg_to, speeds_now, step_s, uavs)
        commanded = np.where(untimed, commanded, timed)
    return CandidateRows(candidates, rows, aims, starts, speeds_now, commanded)
