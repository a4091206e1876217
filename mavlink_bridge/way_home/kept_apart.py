"""The flight home kept d_min apart: which plane flies home now and which waits, and where.

ArduPlane's RTL flies the straight line to home at one altitude (RTL_ALTITUDE, the same for
every plane of a mission), so two planes whose lines home cross fly into each other unless
someone says otherwise (issue 12: two planes 20 m apart on the way home in the simulator;
ArduPlane SITL planes converging on their homes breached separation once in four runs). The
safe return (``around_threats.py``) keeps every way home clear of the threats (C_t); this module
keeps the planes on it apart (C_c, d_min of eq. 4's constraint set), in time as well as space:

* every plane's next stretch home is a :class:`Homeward` leg (``homeward.py``): straight from
  where it is to an aim (its home, or the safe return's waypoint around a threat) at cruise
  speed, then circling the aim;
* two legs **conflict** when at some instant, within the timing's uncertainty, the planes
  would be closer than d_min plus what each may stray from its place (``homeward_flights.py``
  states the rule);
* :meth:`ReturnSeparation.plan` takes the legs that are set (planes already in RTL: nobody can
  hold them any more) and the planes still waiting for their way home, nearest aim first: a
  plane whose leg conflicts with none set flies it (and is set), any other **holds**: it is
  guided to the nearest point whose loiter circle keeps the threat margin and whose leg there
  conflicts with none set, and circles there until a later decision period finds its way clear;
  where no hold point clears it, or only planes circling their homes are in the way (they stay
  there: no wait clears it), it **detours**: it is guided through the nearest point whose way
  (there, then on to its aim) conflicts with none set, re-judged every decision period.
  Two planes both circling their own homes are not compared: where homes are is the
  scenario's choice, not the flight home's.

All geometry is in the mission's local km; times are the vehicles' seconds.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_bridge.way_home.homeward import Homeward
from mavlink_bridge.way_home.homeward_flights import HomewardFlights


@dataclass
class ReturnSeparation(HomewardFlights):
    """Deconflicts the planes' flights home (see the module's docstring): finds the holds,
    detours and staggered departures, and plans who flies home now."""

    #: hold points (``hold``) around the plane, in ``pass_km`` (the simulator's 100 m/s plane:
    #: 2.1 to 8.4 km; a PX4 SIH plane, 80 m circles, d_min 0.6: 0.4 to 1.7 km)
    hold_rings: tuple[float, ...] = (0.0, 0.5, 1.0, 1.5, 2.0)
    hold_directions: int = 16
    #: detour points (``detour``) around the plane, in ``pass_km``: rings fixed in km (3 to
    #: 12) fitted the 100 m/s plane only; on px4-3uav's 4 x 3.2 km area every one was off
    #: the area or in another's way, and a plane flew home through another's home circle
    detour_rings: tuple[float, ...] = (0.75, 1.25, 1.75, 2.25, 3.0)
    #: a hold, detour or staggered departure is chosen this much beyond d_min, and kept while
    #: it keeps d_min: chosen 0.01 km clear, one was condemned 2 s later by the drift of the
    #: prediction, and the plane was left without a way
    choose_margin_km: float = 0.1

    def pass_km(self) -> float:
        """How far off its line a plane must pass a home circle to keep d_min from the plane
        circling there: d_min, the circle's reach and the stray of each (4.2 km for the
        simulator's 100 m/s plane, 0.84 km for PX4's SIH plane at d_min 0.6)."""
        return self.d_min_km + self.circle_km() + self.slack_km

    def _rings(self, xy: np.ndarray, radii: tuple[float, ...]) -> np.ndarray:
        """Points on circles of ``radii`` (in ``pass_km``) around ``xy``, ``hold_directions``
        to a circle, circle by circle (radius 0: ``xy`` itself)."""
        angles = np.arange(self.hold_directions) * (2 * math.pi / self.hold_directions)
        ring = self.pass_km() * np.stack([np.cos(angles), np.sin(angles)], axis=1)
        return np.concatenate([xy[None] if r == 0 else xy[None] + r * ring for r in radii])

    def _circle_and_leg_clear(self, xy: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Points whose circle keeps the threat margin (the loiter diameter from the point)
        and whose leg from ``xy`` keeps it too."""
        routes = self.routes
        keep = routes.point_clearance(points) >= routes.margin_km + self.circle_km()
        leg = routes.leg_clearance(np.broadcast_to(xy, points.shape), points)
        return keep & (leg >= routes.margin_km)

    def hold(
        self,
        leg: Homeward,
        course_rad: float,
        others: list[Homeward],
        previous: np.ndarray | None = None,
    ) -> tuple[np.ndarray, Homeward] | None:
        """The nearest point for the plane of ``leg`` to circle until its way home is clear,
        and its flight there: the circle keeps the threat margin (the loiter diameter from
        the point), the leg there and the turn onto it keep it too, and that flight conflicts
        with none of ``others``; ``previous`` (the point it circles now) first, so a holding
        plane is not moved while its point stays good; ``None`` if no candidate does. Each
        leg is judged as the plane model flies it (``guided_flights``: the turn onto it both
        ways round where it turns about), not as a straight line: a plane sent to hold 4 km
        behind it as a straight leg turned about into another's way home (0.01 km apart at
        10 % loss, 5x)."""
        xy = leg.start_km
        if previous is not None:
            kept = self._still_good(leg, course_rad, others, previous, None)
            if kept is not None:
                return np.asarray(previous, float).copy(), kept
        candidates = self._hold_points(xy, course_rad)
        holds = self.guided_flights(leg.key, xy, course_rad, candidates)
        for point, hold in zip(candidates, holds, strict=True):  # nearest first (ring order)
            if not self.conflicts(hold, others, self.choose_margin_km):
                return point.copy(), hold
        return None

    def _still_good(
        self,
        leg: Homeward,
        course_rad: float,
        others: list[Homeward],
        point: np.ndarray,
        then_km: np.ndarray | None,
    ) -> Homeward | None:
        """The flight to the point a plane holds at (``then_km`` None) or detours through now,
        while it is safe (its circle, the legs and the turn keep the threat margin) and that
        flight (and on) as the plane model flies it conflicts with none of ``others``: judged
        as it was chosen, not by the straight line, which may condemn it a decision period
        later and move the plane for nothing. None when it is not."""
        xy, point = leg.start_km, np.asarray(point, float)
        if len(self._safe_points(xy, course_rad, point[None])) == 0:
            return None
        on_clear = then_km is None or (
            self.routes.leg_clearance(point[None], then_km[None])[0] >= self.routes.margin_km
        )
        if not on_clear:
            return None
        (flight,) = self.guided_flights(leg.key, xy, course_rad, point[None], then_km, leg.at_home)
        return None if self.conflicts(flight, others) else flight

    def detour(
        self,
        leg: Homeward,
        course_rad: float,
        others: list[Homeward],
        previous: np.ndarray | None = None,
    ) -> tuple[np.ndarray, Homeward] | None:
        """A point for the plane of ``leg`` to fly through on its way to its aim, around what
        is in the way (another plane circling its home on the line, or flying home near it),
        and the flight through it: its circle keeps the threat margin (if the ground station
        goes silent the plane circles it), both legs and the turn onto the first keep it
        too, and the way through it conflicts with none of ``others``; ``previous`` (the
        point it flies to now) first, then the shortest way; ``None`` if no candidate does."""
        xy, aim = leg.start_km, leg.aim_km
        if previous is not None:
            kept = self._still_good(leg, course_rad, others, previous, aim)
            if kept is not None:
                return np.asarray(previous, float).copy(), kept
        points = self._detour_points(xy, course_rad, aim)
        ways = self.guided_flights(leg.key, xy, course_rad, points, aim, leg.at_home)
        for point, way in zip(points, ways, strict=True):  # the shortest way first
            if not self.conflicts(way, others, self.choose_margin_km):
                return point.copy(), way
        return None

    def _safe_points(self, xy: np.ndarray, course_rad: float, points: np.ndarray) -> np.ndarray:
        """Of ``points``, those a plane at ``xy`` on ``course_rad`` may be guided to: its
        circle there, the leg and the turn onto it keep the threat margin."""
        routes = self.routes
        points = points[self._circle_and_leg_clear(xy, points)]
        if len(points) == 0:
            return points
        return points[routes.turn_clearance(xy, course_rad, points) >= routes.turn_margin_km]

    def _hold_points(self, xy: np.ndarray, course_rad: float) -> np.ndarray:
        """Safe points to hold at around ``xy``, nearest first (``hold_rings``)."""
        rings = self._rings(xy, (0.0, *(r for r in self.hold_rings if r > 0)))
        return self._safe_points(xy, course_rad, rings)

    def _detour_points(self, xy: np.ndarray, course_rad: float, aim: np.ndarray) -> np.ndarray:
        """Safe points to fly through from ``xy`` on to ``aim`` (the leg on keeps the threat
        margin too), the shortest way first (``detour_rings``)."""
        points = self._rings(xy, self.detour_rings)
        total = np.hypot(*(points - xy).T) + np.hypot(*(aim - points).T)
        points = self._safe_points(xy, course_rad, points[np.argsort(total, kind="stable")])
        on = self.routes.leg_clearance(points, np.broadcast_to(aim, points.shape))
        return points[on >= self.routes.margin_km]

    def stagger(
        self,
        leg: Homeward,
        course_rad: float,
        fixed: list[Homeward],
        blocking: list[Homeward],
        released: dict[VehicleKey, float],
    ) -> tuple[VehicleKey, np.ndarray, np.ndarray | None, Homeward, Homeward] | None:
        """Two planes that end the mission a few km apart with crossing ways: the one cleared
        first (``released``: system id -> course; its way home set in this plan, or already
        flying RTL, which a DO_REPOSITION takes out of it) flies its way through where
        ``leg``'s plane is, and ``leg``'s plane cannot get out of it in time, nor detour
        around it. A staggered departure does: the other plane holds (the nearest safe point
        whose flight there conflicts with none of the rest) and ``leg``'s plane flies its way,
        or the nearest detour, clear of that hold and of the rest. Both are judged as the
        plane model flies them (``guided_flights``): the turn onto each way decides it here.
        Returns (the holding plane, its point, ``leg``'s detour point or None, the hold's
        flight, ``leg``'s flight), or None when no pair clears it (or more than one plane is
        in the way: ``blocking``, those of ``fixed`` ``leg`` conflicts with)."""
        if len(blocking) != 1 or blocking[0].key not in released:
            return None
        other = blocking[0]
        rest = [o for o in fixed if o is not other]
        other_course = released[other.key]
        holds = self._hold_points(other.start_km, other_course)
        detours = self._detour_points(leg.start_km, course_rad, leg.aim_km)
        ways: list[tuple[np.ndarray | None, Homeward]] = [(None, leg)] + list(
            zip(
                detours,
                self.guided_flights(
                    leg.key, leg.start_km, course_rad, detours, leg.aim_km, leg.at_home
                ),
                strict=True,
            )
        )
        margin = self.choose_margin_km
        ways = [(via, way) for via, way in ways if not self.conflicts(way, rest, margin)]
        if not ways:
            return None
        hold_flights = self.guided_flights(other.key, other.start_km, other_course, holds)
        for point, hold in zip(holds, hold_flights, strict=True):
            if self.conflicts(hold, rest, margin):
                continue
            for via, way in ways:
                if not self.conflict(way, hold, margin):
                    return other.key, point.copy(), via, hold, way
        return None

    def plan(
        self,
        set_legs: list[Homeward],
        waiting: list[tuple[Homeward, float]],
        keep: dict[VehicleKey, np.ndarray] | None = None,
        detouring: set[VehicleKey] | frozenset[VehicleKey] = frozenset(),
        movable: dict[VehicleKey, float] | None = None,
    ) -> ReturnPlan:
        """Which of the ``waiting`` planes (their leg home and their course) must hold, and
        where. ``set_legs`` are flights nobody can change any more; ``keep``: the points planes
        hold at or detour through now (``detouring``: those that detour), kept while good.

        A plane holding now keeps its hold (judged as the plane model flies it) while that
        conflicts with none set, and the others are judged against it: a plane that another
        holds for must not then fly through the hold. It flies home once its way conflicts
        with none of what the others do. A plane that conflicts and finds no hold point,
        detour or staggered departure (``stagger``) takes the one of them, or its leg, that
        comes least close (``unresolved``: the daemon says so). ``movable``: of ``set_legs``,
        the planes (system id -> course) that may be guided again to let another leave first
        (planes in RTL: a DO_REPOSITION takes them out of it)."""
        planning = _Planning(keep or {}, movable or {}, list(set_legs))
        order = sorted(waiting, key=lambda lc: (lc[0].arrival_s, lc[0].key))
        for leg, course in order:
            if leg.key not in detouring:
                self._keep_hold(planning, leg, course)
        for leg, course in order:
            if leg.key not in planning.kept:
                self._find_way(planning, leg, course)
        for leg, course in order:
            if leg.key in planning.kept:
                self._end_hold(planning, leg, course)
        return planning.plan

    def _keep_hold(self, planning: _Planning, leg: Homeward, course: float) -> None:
        """A plane holding now keeps its point while its flight there (as the plane model
        flies it) conflicts with none set; the planes after it are judged against it."""
        point = planning.keep.get(leg.key)
        if point is None:
            return
        (hold,) = self.guided_flights(leg.key, leg.start_km, course, point[None])
        if not self.conflicts(hold, planning.fixed):
            planning.kept[leg.key] = hold
            planning.fixed.append(hold)

    def _find_way(self, planning: _Planning, leg: Homeward, course: float) -> None:
        """A waiting plane flies its leg home when it conflicts with none set; else, in this
        order, it holds (unless only planes that stay where they are block it), detours, has
        the plane in its way hold while it leaves first (``stagger``), or takes the way that
        comes least close (``_least_close``)."""
        fixed, plan, sid = planning.fixed, planning.plan, leg.key
        blocking = [o for o in fixed if self.conflict(leg, o)]
        if not blocking:
            fixed.append(leg)
            planning.released[sid] = course
            return
        previous = planning.keep.get(sid)
        # planes already circling their homes stay there, and so do planes holding until
        # this one is out of their way: holding would never clear the way (a plane held
        # for one circled until the watch of the flight home ended): only a detour does
        circling = all(planning.stays(o) for o in blocking)
        found = None if circling else self.hold(leg, course, fixed, previous)
        if found is not None:
            plan.holds[sid], flight = found
            fixed.append(flight)
            return
        found = self.detour(leg, course, fixed, previous)
        if found is not None:
            plan.holds[sid], flight = found
            plan.detours.append(sid)
            fixed.append(flight)
            return
        staggered = self.stagger(
            leg, course, fixed, blocking, {**planning.movable, **planning.released}
        )
        if staggered is None:
            self._least_close(planning, leg, course, fixed)
            return
        other, hold_km, via, hold, way = staggered
        planning.released.pop(other, None)
        plan.holds[other] = hold_km
        plan.staggered[other] = sid
        planning.fixed = [o for o in fixed if o.key != other] + [hold, way]
        if via is None:
            planning.released[sid] = course
        else:
            plan.holds[sid] = via
            plan.detours.append(sid)

    def _least_close(
        self, planning: _Planning, leg: Homeward, course: float, fixed: list[Homeward]
    ) -> None:
        """No way of ``leg``'s plane clears every flight set: it takes the one that comes least
        close to them (``unresolved``: the daemon says so), its leg home, a hold or a detour.
        Flying its leg on regardless took a plane of px4-3uav through the circle of another
        at its home (0.04 km); the planner's missed-claim rule does the same (the move that
        keeps the most separation)."""
        xy, sid = leg.start_km, leg.key
        holds = self._hold_points(xy, course)
        detours = self._detour_points(xy, course, leg.aim_km)
        options: list[tuple[np.ndarray | None, bool, Homeward]] = [(None, False, leg)]
        options += [
            (p, False, f)
            for p, f in zip(holds, self.guided_flights(sid, xy, course, holds), strict=True)
        ]
        options += [
            (p, True, f)
            for p, f in zip(
                detours,
                self.guided_flights(sid, xy, course, detours, leg.aim_km, leg.at_home),
                strict=True,
            )
        ]
        closest = [self.closest_km(f, fixed) for _, _, f in options]
        best = int(np.argmax(closest))
        point, is_detour, flight = options[best]
        planning.plan.unresolved.append(sid)
        planning.plan.closest_km[sid] = closest[best]
        planning.fixed.append(flight)
        if point is None:
            return
        planning.plan.holds[sid] = point.copy()
        if is_detour:
            planning.plan.detours.append(sid)

    def _end_hold(self, planning: _Planning, leg: Homeward, course: float) -> None:
        """A plane holding now flies home once its way is clear of what every other one does;
        where only planes that stay (circling their homes, holding) are in its way, waiting
        does not clear it: it detours. Else it keeps holding."""
        plan, sid = planning.plan, leg.key
        hold = planning.kept[sid]
        others = [o for o in planning.fixed if o is not hold]
        blocking = [o for o in others if self.conflict(leg, o)]
        if not blocking:
            planning.fixed = [*others, leg]
            return
        if not all(planning.stays(o) for o in blocking):
            plan.holds[sid] = planning.keep[sid]
            return
        found = self.detour(leg, course, others)
        if found is None:
            planning.fixed = others
            self._least_close(planning, leg, course, others)
            return
        plan.holds[sid], flight = found
        plan.detours.append(sid)
        planning.fixed = [*others, flight]


@dataclass
class ReturnPlan:
    """What :meth:`ReturnSeparation.plan` decided for the planes waiting for their way home."""

    holds: dict[VehicleKey, np.ndarray] = field(default_factory=dict)  # vehicle -> point to fly to
    #: of ``holds``, the planes that fly through their point on the way (a detour), not wait
    detours: list[VehicleKey] = field(default_factory=list)
    #: conflicting whatever they do: each takes the way that comes least close (a hold or a
    #: detour in ``holds``, else its leg home), ``closest_km`` to the others less their strays
    unresolved: list[VehicleKey] = field(default_factory=list)
    closest_km: dict[VehicleKey, float] = field(default_factory=dict)
    #: of ``holds``, planes held so that another can leave first (``stagger``): -> that plane
    staggered: dict[VehicleKey, VehicleKey] = field(default_factory=dict)

    def news(
        self, holding: Iterable[VehicleKey], unresolved: Iterable[VehicleKey]
    ) -> list[str]:
        """What the daemon says of this plan: each plane newly unresolved (not in
        ``unresolved``), staggered, or newly holding or detouring (not in ``holding``)."""
        lines, holding = [], set(holding)
        for sid in sorted(set(self.unresolved) - set(unresolved)):
            point = self.holds.get(sid)
            how = "it flies via" if sid in self.detours else "it holds at"
            does = "it flies on" if point is None else f"{how} ({point[0]:.1f}, {point[1]:.1f}) km"
            lines.append(
                f"warning: no way home for vehicle {sid} keeps d_min from every other plane's "
                f"for sure: {does}, the way that keeps farthest from them "
                f"({self.closest_km[sid]:.2f} km, their strays counted)"
            )
        for sid, point in self.holds.items():
            at = f"({point[0]:.1f}, {point[1]:.1f}) km"
            if sid in self.staggered:
                lines.append(
                    f"vehicle {sid} holds at {at} while vehicle {self.staggered[sid]} leaves "
                    "first: their ways home cross, and they are too close for either to wait "
                    "or go around the other alone"
                )
            elif sid not in self.unresolved and sid not in holding:
                how = "flies home via" if sid in self.detours else "holds at"
                lines.append(
                    f"vehicle {sid} {how} {at}: its way home would come within d_min of "
                    "another plane's"
                )
        return lines


@dataclass
class _Planning:
    """One :meth:`ReturnSeparation.plan` as it goes."""

    keep: dict[VehicleKey, np.ndarray]  # the points planes hold at or detour through now
    movable: dict[VehicleKey, float]  # set planes that may be guided again: system id -> course
    fixed: list[Homeward]  # the flights set so far: each plane is judged against them
    plan: ReturnPlan = field(default_factory=ReturnPlan)
    #: planes holding at the point they hold at now: their flight there
    kept: dict[VehicleKey, Homeward] = field(default_factory=dict)
    #: waiting planes whose way is set as it is: their course
    released: dict[VehicleKey, float] = field(default_factory=dict)

    def stays(self, other: Homeward) -> bool:
        """``other`` stays where it is whatever the plane judged against it does: it circles
        its home, or holds (until that plane is out of its way)."""
        return (other.at_home and other.settled) or other.key in self.kept
