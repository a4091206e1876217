"""What the UAVs of a swarm without a centre tell each other at one decision step (section 3.3.1:
each UAV keeps its own beliefs and hears its neighbours), as plain data a codec can put on a
radio: ints, floats, bools and tuples of them, never arrays.

A step k is four exchanges (``planner.uav_node.UavNode``, ``planner.swarm_bus.SwarmBus``):

1. ``UavState``, ``Look``, ``Engagements``, ``ThreatsFound``: what each UAV is and found;
2. ``TrackIntent``: the cell it goes for and its place in C_c's claim order;
3. ``CellClaim``: the cell it takes next, in claim order (a UAV claims after the higher-priority
   neighbours it might meet); a ``CellClaim`` may ask a blocker to step aside (``displace``),
   and the blocker's new ``CellClaim`` answers it.

Ranges: a ``uav`` is 0..N-1 (N the swarm's size), ``step`` 0..the mission's steps, a cell
``(ix, iy)`` is 0..grid_nx-1, 0..grid_ny-1 ((-1, -1): none), a heading 0..7
(``planner.grid.HEADING_STEPS``), positions in km inside the area, a target id as the
scenario's (a non-negative int), a threat index 0..T-1 in the scenario's order.
"""

from __future__ import annotations

from dataclasses import dataclass

Cell = tuple[int, int]
NO_CELL: Cell = (-1, -1)


@dataclass(frozen=True)
class UavState:
    """Where a UAV is at step ``step``."""

    uav: int
    step: int
    cell: Cell
    heading: int  # 0..7
    position_km: tuple[float, float]  # measured (the cell's centre without a measure)
    radius_km: float  # its cooperative radius (eqs 1-3), coop_radius_min_km..sensing_radius_km
    flying: bool  # False: done (home) or unreachable; it holds its cell
    #: measured course over ground (rad counter-clockwise from east) and ground speed (m/s) at
    #: the decision instant, where a flown UAV says them (its neighbours' flight envelopes
    #: predict its flight from them); None: not measured (the planner never uses them)
    course_rad: float | None = None
    speed_mps: float | None = None


@dataclass(frozen=True)
class Look:
    """One look of the UAV's sensor (``planner.sensor_model.SensorReport``)."""

    uav: int
    step: int
    cells: tuple[Cell, ...]  # the footprint's cells (at most ``PlannerConfig.footprint_cells``)
    detected: tuple[bool, ...]  # one detection bit per cell


@dataclass(frozen=True)
class Engagements:
    """The UAV's engagement outcome of this step and every serviced target it knows of."""

    uav: int
    step: int
    #: its own outcome: (target id, 1 engaged / 0 missed, cell of the request), or None
    outcome: tuple[int, int, Cell] | None
    serviced: tuple[tuple[int, Cell], ...]  # (target id, cell where it was engaged)


@dataclass(frozen=True)
class ThreatsFound:
    """The threats the UAV has found or heard of (indices into the scenario's threats)."""

    uav: int
    step: int
    threats: tuple[int, ...]


@dataclass(frozen=True)
class TrackIntent:
    """The cell the UAV goes for (one UAV per target: the nearer keeps it) and its C_c
    priority (``planner.transition.claim_priority``: smaller claims first)."""

    uav: int
    step: int
    track: Cell  # NO_CELL: none
    priority: int  # allowed moves * N + uav, 0..(C + 1) * N


@dataclass(frozen=True)
class CellClaim:
    """The cell the UAV takes at the next step, with its other allowed cells in its order of
    preference (so a lower-priority neighbour boxed in may ask it to step aside)."""

    uav: int
    step: int
    cell: Cell  # the claimed cell (its current one when it holds)
    heading: int  # 0..7 after the move
    alternatives: tuple[Cell, ...]  # its allowed candidate cells, preferred first (at most 8)
    displace: tuple[int, Cell] | None = None  # (blocker uav, cell it is asked to take)


Message = UavState | Look | Engagements | ThreatsFound | TrackIntent | CellClaim
