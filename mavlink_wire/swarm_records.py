"""The records of one node's report on the swarm link (docs/onboard.md, "The wire format"):
what a UAV tells its neighbours at a decision step, before :mod:`mavlink_wire.swarm_wire`
encodes it. Importable from there too."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "Claim", "Engagement", "Intent", "Look", "MoveClaim", "NodeState", "SwarmReport",
    "ThreatReport",
]  # fmt: skip


@dataclass(frozen=True)
class NodeState:
    """Where a UAV is at its decision step: its cell and heading (0-7, the grid's), measured
    position (km, sent in whole metres) and cooperative radius r_i (km, sent exactly)."""

    cell: tuple[int, int]
    heading: int
    x_km: float
    y_km: float
    coop_radius_km: float
    flying: bool = True  # False: done (home) or unreachable; it holds its cell
    #: measured course over ground (rad counter-clockwise from east, sent in 1/100 degree) and
    #: ground speed (m/s, sent in cm/s) at the decision instant; None: not measured (not sent)
    course_rad: float | None = None
    speed_mps: float | None = None


@dataclass(frozen=True)
class Look:
    """One sensor look: UAV ``uav``'s look at ``step`` centred on ``cell``; ``detected`` holds
    one bit per footprint cell, in the order of ``Grid.disc_offsets(detection_radius_km)``
    (cells outside the area are sent as False and ignored by the receiver)."""

    uav: int
    step: int
    cell: tuple[int, int]
    detected: tuple[bool, ...]


@dataclass(frozen=True)
class Engagement:
    """An engagement's outcome: target id (0: none there), the cell it was asked at, the step,
    and whether the target was confirmed and serviced."""

    target_id: int
    cell: tuple[int, int]
    step: int
    success: bool


@dataclass(frozen=True)
class Claim:
    """The cell a UAV claims for its next move (C_c), in claim round ``round``."""

    cell: tuple[int, int]
    round: int


@dataclass(frozen=True)
class Intent:
    """The cell a UAV goes for (``NO_CELL_WIRE``: none) and its C_c priority (smaller claims
    first), ``planner.swarm_messages.TrackIntent``."""

    track: tuple[int, int]
    priority: int


@dataclass(frozen=True)
class MoveClaim:
    """The cell a UAV takes next with its heading after the move, its other allowed cells in
    its order of preference, and a request to a blocker to step aside (``displace``: (blocker
    UAV, cell it is asked to take) or None), ``planner.swarm_messages.CellClaim``."""

    cell: tuple[int, int]
    heading: int
    alternatives: tuple[tuple[int, int], ...] = ()
    displace: tuple[int, tuple[int, int]] | None = None


@dataclass(frozen=True)
class ThreatReport:
    """A threat zone the UAV has found or heard of (km; sent in whole metres)."""

    x_km: float
    y_km: float
    radius_km: float


@dataclass(frozen=True)
class SwarmReport:
    """What one node tells its neighbours at one decision step (any part may be empty: a claim
    round sends only ``claims``)."""

    uav: int
    step: int
    state: NodeState | None = None
    looks: tuple[Look, ...] = ()
    engagements: tuple[Engagement, ...] = ()
    serviced: tuple[int, ...] = ()
    claims: tuple[Claim, ...] = ()
    threats: tuple[ThreatReport, ...] = ()
    intent: Intent | None = None
    moves: tuple[MoveClaim, ...] = ()
    serviced_at: tuple[tuple[int, tuple[int, int]], ...] = ()  # (target id, cell engaged at)
