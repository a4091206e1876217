"""The neighbours' flights a planner node (``swarmplan node``) keeps its own flight apart from.

The central daemon's flight envelope (``flight_envelope.py``) predicts every plane's flight over
the step and settles the UAVs in index order, each kept apart from the predicted flights of
those settled before it (and, when it has no safe target left, re-opening the choice of the one
it comes closest to). A node flies one plane, so it predicts its neighbours' flights from what
they said on the swarm link (:class:`HeardFlight`: their state at the decision instant, with the
measured course and ground speed, and the cell they claimed) and hands them to the same envelope
(:class:`NeighbourFlights`, ``FlightEnvelope.choose``'s ``neighbours``): the same prediction,
the same lossy-link variants, the same separation rule and candidates (another cell, keep going,
circle here).

Which neighbours, and flying where (:func:`neighbour_flights`), of those whose position now may
be within ``reach_km`` of this plane's:

* a neighbour heard this step whose claim was heard is settled with this node's plane exactly as
  the central daemon settles the pair: in UAV order, each on its own envelope's candidates (its
  claimed cell first; another cell, keep going, circle here), the repair included. Its own node
  settles the same pair from the same messages, so the two take the choices the central
  settling gives them (in lockstep exactly; paced, from positions the neighbour's node measures
  and this one advances);
* a neighbour heard this step whose claim was not heard (lost, or late) is taken to fly on to the
  target it flew to at the decision instant (the one its cell and claim of the step before stand
  for; straight on along its course when that is not known either): with no new target a plane
  flies on to its last one. Its flight is given: this plane keeps apart from it;
* a neighbour not heard this step (its state lost or out of range), heard at most
  ``planner.claim_deadline.PREDICT_STEPS`` steps ago: its last heard state advanced. It is taken
  to have flown on from where it was then to the target its claim of that step stood for (or
  straight on along its course, without one) until now, and to fly on to it; given. This is the
  worst reasonable guess without its newer targets: it keeps this plane clear of where the
  neighbour was heading, which is where a plane that lost its link goes;
* a neighbour that is done or unreachable (not flying) circles its cell; given.

A neighbour whose course or speed was not said is taken to fly along its grid heading at cruise
speed. Every neighbour is taken to fly the node's own airframe, from the home of its scenario
start, having flown nothing the range rule counts (not said on the link).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from mavlink_bridge.safety.safety_envelope import SafetyEnvelope
from mavlink_bridge.vehicles.flight_prediction import PlaneModel, predict_paths
from planner.grid import HEADING_STEPS

#: how far ahead (km) a neighbour with no known target is taken to aim along its course
STRAIGHT_ON_KM = 20.0


@dataclass(frozen=True)
class HeardFlight:
    """What a node heard of one neighbour (plain data, from the swarm link)."""

    uav: int
    age_steps: int  # 0: its state of this step; k: heard k steps ago, nothing since
    position_km: tuple[float, float]  # measured at its decision instant
    course_rad: float | None  # measured course over ground, rad from east (None: not said)
    speed_mps: float | None  # measured ground speed (None: not said)
    cell: tuple[int, int]
    heading: int  # 0..7
    flying: bool
    #: the cell (and heading) it claimed at that step; None: its claim was not heard
    claim: tuple[int, int] | None = None
    claim_heading: int = 0
    #: the cell it was in and the cell it claimed at the step before (its target meanwhile)
    flown_leg: tuple[tuple[int, int], tuple[int, int]] | None = None
    home_km: tuple[float, float] = (0.0, 0.0)  # its scenario start


@dataclass(frozen=True)
class NeighbourFlights:
    """K neighbours' flights as the flight envelope takes them: where each is now and how it
    flies, the cell it claimed (``free``: settled with the node's plane on its candidates) or
    stands for, and the guided target of a given flight (flown at cruise)."""

    own_uav: int  # the node's own UAV
    uavs: np.ndarray  # (K,) the scenario's UAV of each
    free: np.ndarray  # (K,) bool: settled on its own candidates (its claim heard); else given
    positions_km: np.ndarray  # (K, 2) now
    courses_rad: np.ndarray  # (K,)
    speeds_mps: np.ndarray  # (K,)
    cells: np.ndarray  # (K, 2) where it was at the decision instant
    headings: np.ndarray  # (K,) its heading there
    homes_km: np.ndarray  # (K, 2)
    claimed_cells: np.ndarray  # (K, 2)
    claimed_headings: np.ndarray  # (K,)
    aims_km: np.ndarray  # (K, 2) a given flight's target (a free one's claim's aim)
    previous_aims_km: np.ndarray  # (K, 2) the target it flew to before (nan: not known)

    def __len__(self) -> int:
        return len(self.uavs)

    def settling_order(self, own: int) -> tuple[int, ...]:
        """The envelope's rows (``own`` UAVs of this node, then these) in the order the central
        daemon settles them: by the scenario's UAV."""
        uavs = [self.own_uav + i for i in range(own)] + [int(u) for u in self.uavs]
        return tuple(sorted(range(len(uavs)), key=lambda r: uavs[r]))


def _aims(
    heard: Sequence[HeardFlight], env: SafetyEnvelope, lead: float, courses: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each neighbour's target since its state was said (its flown leg's aim, else straight on
    along its course; an old claim's aim; its cell's centre when it does not fly), the cell and
    heading it stands for now and the target it flies to now, and whether that is this step's
    claim (timed)."""
    grid = env.grid
    before, cells, headings, aims, timed = [], [], [], [], []
    for f, course in zip(heard, courses, strict=True):
        here = np.asarray(f.cell)
        on = np.asarray(f.position_km) + STRAIGHT_ON_KM * np.array([np.cos(course),
                                                                    np.sin(course)])  # fmt: skip
        if f.flown_leg is not None:
            on = env.aim_point_km(np.asarray(f.flown_leg[0]), np.asarray(f.flown_leg[1]), lead)
        claimed = False
        if not f.flying:
            cell, heading, aim = here, f.heading, grid.centre_km(here)
            on = aim
        elif f.claim is not None:
            cell, heading = np.asarray(f.claim), f.claim_heading
            aim, claimed = env.aim_point_km(here, cell, lead), f.age_steps == 0
            if not claimed:  # an old claim: the target it was sent to then, flown on
                on = aim
        else:
            cell, heading, aim = here + HEADING_STEPS[f.heading], f.heading, on
        before.append(on)
        cells.append(cell)
        headings.append(heading)
        aims.append(aim)
        timed.append(claimed)
    return (np.array(before, float).reshape(-1, 2), np.array(cells, int).reshape(-1, 2),
            np.array(headings, int), np.array(aims, float).reshape(-1, 2),
            np.array(timed, bool))  # fmt: skip


def neighbour_flights(
    heard: Sequence[HeardFlight],
    own_uav: int,
    env: SafetyEnvelope,
    model: PlaneModel,
    step_s: float,
    lead: float,
    elapsed_s: float,
    here_km: np.ndarray | None = None,
    reach_km: float = np.inf,
) -> NeighbourFlights | None:
    """The flights of the neighbours in ``heard`` that this node (UAV ``own_uav``, its plane
    at ``here_km`` now) settles with or keeps apart from (see the module docstring), advanced
    to now: ``elapsed_s`` after this step's decision instant (paced time; 0 in lockstep), and
    ``age_steps`` decision periods more for a neighbour last heard earlier; only those within
    ``reach_km`` of ``here_km`` now. None when there are none."""
    keep = [f for f in heard if f.uav != own_uav]
    if not keep:
        return None
    courses = np.array([
        f.heading * np.pi / 4 if f.course_rad is None else f.course_rad for f in keep
    ])  # fmt: skip
    speeds = np.array([
        model.speed_mps if f.speed_mps is None or f.speed_mps <= 1.0 else f.speed_mps
        for f in keep
    ])  # fmt: skip
    starts = np.array([f.position_km for f in keep], dtype=float).reshape(-1, 2)
    before, cells, headings, aims, timed = _aims(keep, env, lead, courses)
    since = np.array([f.age_steps * step_s + elapsed_s for f in keep])
    positions, courses = starts.copy(), courses.copy()
    moving = since >= 1.0
    if moving.any():
        flown = predict_paths(model, starts[moving], courses[moving], before[moving],
                              float(since[moving].max()), speed_mps=speeds[moving])  # fmt: skip
        at = np.round(since[moving]).astype(int)
        rows = np.arange(int(moving.sum()))
        here, last = flown[rows, at], flown[rows, at - 1]
        positions[moving] = here
        courses[moving] = np.arctan2(here[:, 1] - last[:, 1], here[:, 0] - last[:, 0])
    near = np.ones(len(keep), dtype=bool)
    if here_km is not None:
        near = np.hypot(*(positions - np.asarray(here_km, dtype=float)).T) <= reach_km
    if not near.any():
        return None
    return NeighbourFlights(
        own_uav=int(own_uav),
        uavs=np.array([f.uav for f in keep], dtype=int)[near],
        free=timed[near],
        positions_km=positions[near],
        courses_rad=courses[near],
        speeds_mps=speeds[near],
        cells=np.array([f.cell for f in keep], dtype=int).reshape(-1, 2)[near],
        headings=np.array([f.heading for f in keep], dtype=int)[near],
        homes_km=np.array([f.home_km for f in keep], dtype=float).reshape(-1, 2)[near],
        claimed_cells=cells[near],
        claimed_headings=headings[near],
        aims_km=aims[near],
        previous_aims_km=before[near],
    )


def model_with_neighbours(model: PlaneModel, own: int, count: int) -> PlaneModel:
    """``model`` for ``own`` UAVs and ``count`` neighbours after them, each flying the airframe
    of UAV 0 (a planner node's own) where the UAVs have airframes of their own."""
    speeds, turns = model.uav_speed_ranges_mps, model.uav_turn_limits
    return replace(
        model,
        uav_speed_ranges_mps=speeds[:own] + speeds[:1] * count if speeds else (),
        uav_turn_limits=turns[:own] + turns[:1] * count if turns else (),
    )


def joined_inputs(own: tuple, neighbours: NeighbourFlights, home_km: np.ndarray) -> tuple:
    """The per-UAV inputs of ``choose`` (positions .. active) with the neighbours' after the
    own UAVs' (the range rule counts nothing flown by a neighbour: not said on the link)."""
    k = len(neighbours)
    theirs = (
        neighbours.positions_km, neighbours.courses_rad, neighbours.speeds_mps, neighbours.cells,
        neighbours.headings, neighbours.claimed_cells, neighbours.claimed_headings,
        neighbours.previous_aims_km, np.zeros(k), neighbours.homes_km, np.ones(k, dtype=bool),
    )  # fmt: skip
    return tuple(
        np.concatenate([np.asarray(a), np.asarray(b, dtype=np.asarray(a).dtype)])
        for a, b in zip(own, theirs, strict=True)
    )
