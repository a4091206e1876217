"""The flight home kept d_min apart: which plane flies home now and which waits, and where.

ArduPlane's RTL flies the straight line to home at one altitude (RTL_ALTITUDE, the same for
every plane of a mission), so two planes whose lines home cross fly into each other unless
someone says otherwise (issue 12: two planes 20 m apart on the way home in the simulator;
ArduPlane SITL planes converging on their homes breached separation once in four runs). The
safe return (``safe_return.py``) keeps every way home clear of the threats (C_t); this module
keeps the planes on it apart (C_c, d_min of eq. 4's constraint set), in time as well as space:

* every plane's next stretch home is a :class:`Homeward` leg: straight from where it is to an
  aim (its home, or the safe return's waypoint around a threat) at cruise speed, then circling
  the aim;
* two legs **conflict** when at some instant the planes would be closer than d_min plus what each
  may stray from its line: ``slack_km`` on the way (the turn onto the line, a wider turn than
  the model), the circle's reach at the aim (a plane that arrives flying straight at its loiter
  point overshoots it by up to a loiter diameter), and never more than it has flown by then
  (two planes 2 km apart now, as the mission leaves them, are not a conflict by themselves).
  Timing is uncertain (a plane held to cruise may fly slower or faster, commands arrive late),
  so a plane at instant t is compared with the other one anywhere in
  ``t +- (tolerance_s + tolerance_frac * t)``;
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
from dataclasses import dataclass, field, replace

import numpy as np

from mavlink_bridge.flight_prediction import PlaneModel, predict_paths, wrap_angle
from mavlink_bridge.safe_return import HomeRoutes

#: how long the plane model's place on a loiter circle is trusted: beyond, a circling plane is
#: anywhere on its circle (its phase drifts with every late command and gust)
PHASE_TRUSTED_S = 20.0


@dataclass(frozen=True)
class Homeward:
    """One plane's next stretch home as predicted: straight to ``aim_km`` at ``speed_kmps``
    (through ``via_km`` first, when it detours), then circling it (straying ``circle_km`` from
    it); ``at_home``: the aim is its home. With ``path_km`` (RTL home from where the plane
    is, its course and speed known: :meth:`ReturnSeparation.flights_home`) the flight is the
    plane model's (the turn onto the way, the overshoot, the circle), every ``path_dt_s``."""

    system_id: int
    start_km: np.ndarray  # (2,)
    aim_km: np.ndarray  # (2,)
    speed_kmps: float
    circle_km: float
    at_home: bool
    via_km: np.ndarray | None = None  # (2,) a detour point flown through on the way
    path_km: np.ndarray | None = None  # (S + 1, 2) predicted positions from now
    path_dt_s: float = 2.0
    path_arrival_s: float = 0.0  # when the predicted path reaches its circle
    #: the same flight turning about the other way (``ReturnSeparation.turns_about_rad``)
    alternatives: tuple[Homeward, ...] = ()

    @property
    def variants(self) -> tuple[Homeward, ...]:
        return (self, *self.alternatives)

    @property
    def length_km(self) -> float:
        if self.via_km is None:
            return float(np.hypot(*(self.aim_km - self.start_km)))
        return float(np.hypot(*(self.via_km - self.start_km))) + float(
            np.hypot(*(self.aim_km - self.via_km))
        )

    @property
    def predicted(self) -> bool:
        return self.path_km is not None

    @property
    def settled(self) -> bool:
        """Already on its circle around the aim (within its loiter radius and a fifth): it
        strays its radius from the aim, not the overshoot of a plane arriving there."""
        return self.via_km is None and self.length_km <= 0.6 * self.circle_km

    @property
    def stray_at_aim_km(self) -> float:
        """How far from its aim it strays once there: its loiter radius when settled, else a
        loiter diameter (``circle_km``: it passes the point before it turns onto its circle)."""
        return self.circle_km / 2 if self.settled else self.circle_km

    @property
    def arrival_s(self) -> float:
        if self.path_km is not None:
            return self.path_arrival_s
        return self.length_km / max(self.speed_kmps, 1e-6)

    def circling(self, t_s: np.ndarray) -> np.ndarray:
        """At which instants a predicted flight counts as anywhere on its circle: once it is
        there and ``PHASE_TRUSTED_S`` from now (the model's place on the circle is trusted
        that long: a plane on its circle now is where it is, not anywhere on it)."""
        t = np.asarray(t_s, float)
        return (t >= self.path_arrival_s) & (t >= PHASE_TRUSTED_S)

    def positions(self, t_s: np.ndarray) -> np.ndarray:
        """(len(t_s), 2) where the plane is at each instant: at the aim once arrived (on a
        predicted path too: where on its circle a plane will be minutes ahead is not known, so
        the whole circle is its place, ``ReturnSeparation._stray_km``)."""
        if self.path_km is not None:
            t = np.asarray(t_s, float)
            index = np.rint(t / self.path_dt_s).astype(int)
            out = self.path_km[np.clip(index, 0, len(self.path_km) - 1)]
            return np.where(self.circling(t)[:, None], self.aim_km[None], out)
        flown = np.clip(np.asarray(t_s, float) * self.speed_kmps, 0.0, self.length_km)
        corners = [self.start_km] + ([] if self.via_km is None else [self.via_km]) + [self.aim_km]
        out = np.repeat(self.start_km[None], len(flown), axis=0)
        done = 0.0
        for a, b in zip(corners[:-1], corners[1:], strict=True):
            length = float(np.hypot(*(b - a)))
            frac = np.clip((flown - done) / max(length, 1e-9), 0.0, 1.0)
            here = flown >= done
            out[here] = a[None] + frac[here, None] * (b - a)[None]
            done += length
        return out


@dataclass
class ReturnSeparation:
    """Deconflicts the planes' flights home (see the module's docstring)."""

    routes: HomeRoutes  # the threats, their margin and the plane model
    d_min_km: float  # d_min of C_c
    slack_km: float  # what a plane may stray from its straight line on the way
    tolerance_s: float = 10.0  # timing uncertainty: fixed part ...
    tolerance_frac: float = 0.15  # ... and the part growing with the time ahead
    sample_s: float = 2.0  # instants compared, this far apart (at 100 m/s: 0.2 km)
    hold_rings_km: tuple[float, ...] = (0.0, 2.0, 4.0, 6.0, 8.0)
    hold_directions: int = 16
    #: detour points (``detour``), this far from the plane: far enough to pass a home
    #: circle off the line by d_min plus the circle's reach and the plane's stray (~4.2 km)
    detour_rings_km: tuple[float, ...] = (3.0, 5.0, 7.0, 9.0, 12.0)
    #: planes that fly home slower than cruise (``home_circle_speeds``), by system id
    speeds_mps: dict[int, float] = field(default_factory=dict)
    #: how far a plane may be from where the plane model flies it (``flights_home``)
    track_km: float = 0.3
    #: a plane whose aim is more than this off its nose may turn about either way (the
    #: simulator's plane, circling clockwise when its RTL came, turned right where the model
    #: turned left, and passed 0.22 km from a plane circling its home: 30 % loss, 20x)
    turns_about_rad: float = 2 * math.pi / 3
    #: a hold, detour or staggered departure is chosen this much beyond d_min, and kept while
    #: it keeps d_min: chosen 0.01 km clear, one was condemned 2 s later by the drift of the
    #: prediction, and the plane was left without a way
    choose_margin_km: float = 0.1

    def circle_km(self) -> float:
        """How far a plane strays from the point it circles: its loiter diameter (it arrives
        flying straight at the point, passes it, and only then turns onto its circle)."""
        return float(self.routes.plane.loiter_reach_km())

    def leg(
        self,
        system_id: int,
        xy_km: np.ndarray,
        aim_km: np.ndarray,
        at_home: bool,
        via_km: np.ndarray | None = None,
    ) -> Homeward:
        plane = self.routes.plane
        # RTL home at the home circle's speed; guided (to a hold, through a detour) at cruise,
        # which an autopilot goes back to at each change of mode (ArduPlane)
        home_mps = self.speeds_mps.get(system_id, plane.speed_mps) if at_home else plane.speed_mps
        travel_mps = home_mps if via_km is None else plane.speed_mps
        return Homeward(
            system_id,
            np.asarray(xy_km, float),
            np.asarray(aim_km, float),
            travel_mps / 1e3,
            float(plane.loiter_reach_km(home_mps)),
            at_home,
            None if via_km is None else np.asarray(via_km, float),
        )

    def flights_home(
        self, ways: list[tuple[int, np.ndarray, np.ndarray, float, float]]
    ) -> list[Homeward]:
        """The RTL flights home of planes (system id, where, home, course in rad from east,
        airspeed now), each as the plane model flies it (``predict_paths``, all in one batch):
        the turn from its course onto the way home, at the home circle's speed
        (``speeds_mps``) once commanded, the overshoot at home and the circle. The straight line
        and its strays (``leg``) would miss a plane that turns the long way round, past
        another's home circle (paper-10uav seed 3: 0.79 km)."""
        if not ways:
            return []
        plane = self.routes.plane
        ids = [w[0] for w in ways]
        xy = np.array([w[1] for w in ways], float)
        home = np.array([w[2] for w in ways], float)
        course = np.array([w[3] for w in ways], float)
        now = np.array([w[4] for w in ways], float)
        home_mps = np.array([self.speeds_mps.get(i, plane.speed_mps) for i in ids])
        radius = np.asarray(plane.loiter_radius_km(home_mps), float)
        straight_s = np.hypot(*(home - xy).T) * 1e3 / home_mps
        # a half turn, the way, and a circle at home
        turn_s = math.pi / float(plane.turn_rate_radps(float(now.max())))
        horizon = float((straight_s + turn_s + 2 * math.pi * radius * 1e3 / home_mps).max())
        flown = self._flown(xy, course, home, horizon + self.sample_s, now, home_mps)
        return [
            self._predicted(sid, xy[k], home[k], home_mps[k], radius[k], True, flown[k])
            for k, sid in enumerate(ids)
        ]

    def _predicted(
        self,
        system_id: int,
        xy: np.ndarray,
        aim: np.ndarray,
        speed_mps: float,
        radius_km: float,
        at_home: bool,
        paths: list[np.ndarray],
        via: np.ndarray | None = None,
    ) -> Homeward:
        """One plane's flight from its predicted paths (the first, and the other ways round
        as ``alternatives``): each arrives when it first comes within 1.1 loiter radii of
        ``aim`` (else at its end) and then circles it."""
        variants = []
        for path in paths:
            near = np.hypot(*(path - aim).T) <= 1.1 * radius_km
            arrival = float(np.argmax(near) if near.any() else len(path) - 1) * self.sample_s
            variants.append(
                Homeward(
                    system_id,
                    xy,
                    aim,
                    speed_mps / 1e3,
                    2 * radius_km,
                    at_home,
                    via_km=via,
                    path_km=path,
                    path_dt_s=self.sample_s,
                    path_arrival_s=arrival,
                )
            )
        return replace(variants[0], alternatives=tuple(variants[1:]))

    def _flown(
        self,
        xy: np.ndarray,
        course: np.ndarray,
        aims: np.ndarray,
        horizon_s: float,
        speed_mps: np.ndarray | None = None,
        commanded_mps: np.ndarray | None = None,
    ) -> list[list[np.ndarray]]:
        """Per plane (M, all in one batch), its paths as the plane model flies them to its aim:
        the shorter turn, and, when the aim is more than ``turns_about_rad`` off its nose, the
        other way round too."""
        plane = self.routes.plane
        m = len(xy)
        speed = np.broadcast_to(plane.speed_mps if speed_mps is None else speed_mps, (m,))
        commanded = speed if commanded_mps is None else np.broadcast_to(commanded_mps, (m,))
        bearing = np.arctan2(*(aims - xy).T[::-1])
        off = wrap_angle(bearing - course)
        about = np.abs(off) > self.turns_about_rad
        rows = np.concatenate([np.arange(m), np.nonzero(about)[0]])
        sign = np.concatenate([np.zeros(m), -np.sign(off[about])])
        paths = predict_paths(
            plane, xy[rows], course[rows], aims[rows], horizon_s, sample_s=self.sample_s,
            dt_s=0.5, speed_mps=speed[rows], commanded_mps=commanded[rows], turn_sign=sign,
        )  # fmt: skip
        flown: list[list[np.ndarray]] = [[] for _ in range(m)]
        for row, path in zip(rows, paths, strict=True):
            flown[row].append(path)
        return flown

    def clearance_km(self, a: Homeward, b: Homeward) -> float:
        """The smallest distance between ``a`` and ``b`` less what both may stray, over every
        pair of instants within the timing tolerance and every variant of each (the turns
        about either way; < ``d_min_km``: they conflict)."""
        return min(self._clearance_km(x, y) for x in a.variants for y in b.variants)

    def _clearance_km(self, a: Homeward, b: Homeward) -> float:
        horizon = max(a.arrival_s, b.arrival_s)
        horizon = horizon * (1 + self.tolerance_frac) + self.tolerance_s + self.sample_s
        t = np.arange(0.0, horizon + self.sample_s, self.sample_s)
        pa, pb = a.positions(t), b.positions(t)
        gap = np.hypot(*(pa[:, None, :] - pb[None, :, :]).transpose(2, 0, 1))
        arrived_a, arrived_b = t >= a.arrival_s, t >= b.arrival_s
        # no plane strays from its line further than it has flown (planes near each other now
        # are not a conflict by themselves), nor, on the way, further than ``slack_km``
        stray_a, stray_b = self._stray_km(a, t), self._stray_km(b, t)
        clear = gap - stray_a[:, None] - stray_b[None, :]
        window = self.tolerance_s + self.tolerance_frac * np.maximum(t[:, None], t[None, :])
        compared = np.abs(t[:, None] - t[None, :]) <= window
        if a.at_home and b.at_home:  # both circling their homes: the scenario's geometry
            compared &= ~(arrived_a[:, None] & arrived_b[None, :])
        if not compared.any():
            return math.inf
        return float(clear[compared].min())

    def _stray_km(self, leg: Homeward, t: np.ndarray) -> np.ndarray:
        """How far ``leg``'s plane may be from its predicted place at each instant: never
        more than it has flown; on a path the plane model flew, ``track_km`` on the way, and
        once it circles (``Homeward.circling``) its circle (the radius it arrives on, 1.1
        loiter radii): the phase on a circle the model predicts drifts (a
        plane passing 1.46 km from the centre of another's home circle was judged 1.03 km
        clear of the predicted phase and passed 0.22 km from the plane, at 30 % loss and 20x);
        on a straight line, ``slack_km`` on the way and its circle's reach once there."""
        flown = leg.speed_kmps * t
        if leg.predicted:
            circle = 0.55 * leg.circle_km  # the circle bounds it: no track error on top
            return np.where(leg.circling(t), circle, np.minimum(self.track_km, flown))
        at_aim = np.minimum(leg.stray_at_aim_km, flown)
        return np.where(t >= leg.arrival_s, at_aim, np.minimum(self.slack_km, flown))

    def conflict(self, a: Homeward, b: Homeward, margin_km: float = 0.0) -> bool:
        """``clearance_km(a, b) < d_min_km + margin_km``, each pair of variants first judged
        at equal instants alone (a subset of the pairs compared: most conflicts show there, at
        a fraction of the cost)."""
        return any(self._conflict(x, y, margin_km) for x in a.variants for y in b.variants)

    def _conflict(self, a: Homeward, b: Homeward, margin_km: float) -> bool:
        limit = self.d_min_km + margin_km
        horizon = max(a.arrival_s, b.arrival_s) + self.sample_s
        t = np.arange(0.0, horizon + self.sample_s, self.sample_s)
        gap = np.hypot(*(a.positions(t) - b.positions(t)).T)
        clear = gap - self._stray_km(a, t) - self._stray_km(b, t)
        if a.at_home and b.at_home:
            clear = clear[~((t >= a.arrival_s) & (t >= b.arrival_s))]
        if len(clear) and clear.min() < limit:
            return True
        return self._clearance_km(a, b) < limit

    def conflicts(self, leg: Homeward, others: list[Homeward], margin_km: float = 0.0) -> bool:
        return any(self.conflict(leg, o, margin_km) for o in others)

    def _rings(self, xy: np.ndarray, radii_km: tuple[float, ...]) -> np.ndarray:
        """Points on circles of ``radii_km`` around ``xy``, ``hold_directions`` to a circle,
        circle by circle (radius 0: ``xy`` itself)."""
        angles = np.arange(self.hold_directions) * (2 * math.pi / self.hold_directions)
        ring = np.stack([np.cos(angles), np.sin(angles)], axis=1)
        return np.concatenate([xy[None] if r == 0 else xy[None] + r * ring for r in radii_km])

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
        holds = self.guided_flights(leg.system_id, xy, course_rad, candidates)
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
        (flight,) = self.guided_flights(
            leg.system_id, xy, course_rad, point[None], then_km, leg.at_home
        )
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
        ways = self.guided_flights(leg.system_id, xy, course_rad, points, aim, leg.at_home)
        for point, way in zip(points, ways, strict=True):  # the shortest way first
            if not self.conflicts(way, others, self.choose_margin_km):
                return point.copy(), way
        return None

    def guided_flights(
        self,
        system_id: int,
        xy_km: np.ndarray,
        course_rad: float,
        points_km: np.ndarray,
        then_km: np.ndarray | None = None,
        at_home: bool = False,
    ) -> list[Homeward]:
        """The flights of one plane (at ``xy_km`` on ``course_rad``, at cruise) guided to each
        of ``points_km`` (K, 2) as the plane model flies them, in one batch: the turn onto the
        way, the overshoot and the circle there; with ``then_km``, on from each point (once
        within a loiter radius of it, or past it) to ``then_km`` and circling that (a detour).
        Each is a :class:`Homeward` with its path, judged ``track_km`` wide: where planes start
        a few km apart, the straight line and its strays (``leg``) cannot tell a turn away
        from a turn into the other's way."""
        plane = self.routes.plane
        points = np.asarray(points_km, float).reshape(-1, 2)
        if len(points) == 0:
            return []
        xy = np.asarray(xy_km, float)
        speed = plane.speed_mps
        radius_km = float(plane.loiter_radius_km(speed))
        turn_s = math.pi / float(plane.turn_rate_radps(speed))
        circle_s = 2 * math.pi * radius_km * 1e3 / speed

        def horizon(a: np.ndarray, b: np.ndarray) -> float:
            return float(np.hypot(*(b - a).T).max()) * 1e3 / speed + turn_s + circle_s

        starts = np.repeat(xy[None], len(points), axis=0)
        courses = np.full(len(points), float(course_rad))
        flown = self._flown(starts, courses, points, horizon(starts, points))
        owner = np.array([k for k, paths in enumerate(flown) for _ in paths])
        paths = [path for paths in flown for path in paths]  # every variant, candidate by candidate
        aims = points[owner]
        if then_km is not None:
            # leaves each point once within a loiter radius of it, or at its closest approach
            cut = []
            for path, point in zip(paths, aims, strict=True):
                dist = np.hypot(*(path - point).T)
                near = dist <= radius_km
                cut.append(int(np.argmax(near)) if near.any() else int(np.argmin(dist)))
            here = np.array([p[i] for p, i in zip(paths, cut, strict=True)])
            before = np.array([p[max(i - 1, 0)] for p, i in zip(paths, cut, strict=True)])
            heading = np.arctan2(*(here - before).T[::-1])
            aims = np.repeat(np.asarray(then_km, float)[None], len(paths), axis=0)
            onward = predict_paths(
                plane, here, heading, aims, horizon(here, aims), sample_s=self.sample_s, dt_s=0.5
            )
            paths = [
                np.concatenate([p[: i + 1], o[1:]])
                for p, i, o in zip(paths, cut, onward, strict=True)
            ]
        by_point: list[list[np.ndarray]] = [[] for _ in points]
        for k, path in zip(owner, paths, strict=True):
            by_point[k].append(path)
        detour = then_km is not None
        return [
            self._predicted(
                system_id,
                xy,
                np.asarray(then_km, float) if detour else point,
                speed,
                radius_km,
                at_home and detour,
                flown,
                via=point if detour else None,
            )
            for point, flown in zip(points, by_point, strict=True)
        ]

    def _safe_points(self, xy: np.ndarray, course_rad: float, points: np.ndarray) -> np.ndarray:
        """Of ``points``, those a plane at ``xy`` on ``course_rad`` may be guided to: its
        circle there, the leg and the turn onto it keep the threat margin."""
        routes = self.routes
        points = points[self._circle_and_leg_clear(xy, points)]
        if len(points) == 0:
            return points
        return points[routes.turn_clearance(xy, course_rad, points) >= routes.turn_margin_km]

    def _hold_points(self, xy: np.ndarray, course_rad: float) -> np.ndarray:
        """Safe points to hold at around ``xy``, nearest first (``hold_rings_km``)."""
        rings = self._rings(xy, (0.0, *(r for r in self.hold_rings_km if r > 0)))
        return self._safe_points(xy, course_rad, rings)

    def _detour_points(self, xy: np.ndarray, course_rad: float, aim: np.ndarray) -> np.ndarray:
        """Safe points to fly through from ``xy`` on to ``aim`` (the leg on keeps the threat
        margin too), the shortest way first (``detour_rings_km``)."""
        points = self._rings(xy, self.detour_rings_km)
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
        released: dict[int, float],
    ) -> tuple[int, np.ndarray, np.ndarray | None, Homeward, Homeward] | None:
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
        if len(blocking) != 1 or blocking[0].system_id not in released:
            return None
        other = blocking[0]
        rest = [o for o in fixed if o is not other]
        other_course = released[other.system_id]
        holds = self._hold_points(other.start_km, other_course)
        detours = self._detour_points(leg.start_km, course_rad, leg.aim_km)
        ways: list[tuple[np.ndarray | None, Homeward]] = [(None, leg)] + list(
            zip(
                detours,
                self.guided_flights(
                    leg.system_id, leg.start_km, course_rad, detours, leg.aim_km, leg.at_home
                ),
                strict=True,
            )
        )
        margin = self.choose_margin_km
        ways = [(via, way) for via, way in ways if not self.conflicts(way, rest, margin)]
        if not ways:
            return None
        hold_flights = self.guided_flights(other.system_id, other.start_km, other_course, holds)
        for point, hold in zip(holds, hold_flights, strict=True):
            if self.conflicts(hold, rest, margin):
                continue
            for via, way in ways:
                if not self.conflict(way, hold, margin):
                    return other.system_id, point.copy(), via, hold, way
        return None

    def plan(
        self,
        set_legs: list[Homeward],
        waiting: list[tuple[Homeward, float]],
        keep: dict[int, np.ndarray] | None = None,
        detouring: set[int] | frozenset[int] = frozenset(),
        movable: dict[int, float] | None = None,
    ) -> ReturnPlan:
        """Which of the ``waiting`` planes (their leg home and their course) must hold, and
        where. ``set_legs`` are flights nobody can change any more; ``keep``: the points planes
        hold at or detour through now (``detouring``: those that detour), kept while good.

        A plane holding now keeps its hold (judged as the plane model flies it) while that
        conflicts with none set, and the others are judged against it: a plane that another
        holds for must not then fly through the hold. It flies home once its way conflicts
        with none of what the others do. A plane that conflicts and finds no hold point,
        detour or staggered departure (``stagger``) flies its leg (``unresolved``: the daemon
        says so). ``movable``: of ``set_legs``, the planes (system id -> course) that may be
        guided again to let another leave first (planes in RTL: a DO_REPOSITION takes them
        out of it)."""
        keep = keep or {}
        fixed = list(set_legs)
        plan = ReturnPlan()
        order = sorted(waiting, key=lambda lc: (lc[0].arrival_s, lc[0].system_id))
        kept: dict[int, Homeward] = {}  # planes holding at the point they hold at now
        for leg, course in order:
            point = keep.get(leg.system_id)
            if point is None or leg.system_id in detouring:
                continue
            (hold,) = self.guided_flights(leg.system_id, leg.start_km, course, point[None])
            if not self.conflicts(hold, fixed):
                kept[leg.system_id] = hold
                fixed.append(hold)
        released: dict[int, float] = {}  # waiting planes whose way is set as it is: their course
        for leg, course in order:
            if leg.system_id in kept:
                continue
            blocking = [o for o in fixed if self.conflict(leg, o)]
            if not blocking:
                fixed.append(leg)
                released[leg.system_id] = course
                continue
            previous = keep.get(leg.system_id)
            # planes already circling their homes stay there, and so do planes holding until
            # this one is out of their way: holding would never clear the way (a plane held
            # for one circled until the watch of the flight home ended): only a detour does
            circling = all((o.at_home and o.settled) or o.system_id in kept for o in blocking)
            found = None if circling else self.hold(leg, course, fixed, previous)
            if found is not None:
                plan.holds[leg.system_id], flight = found
                fixed.append(flight)
                continue
            found = self.detour(leg, course, fixed, previous)
            if found is not None:
                plan.holds[leg.system_id], flight = found
                plan.detours.append(leg.system_id)
                fixed.append(flight)
                continue
            staggered = self.stagger(leg, course, fixed, blocking, {**(movable or {}), **released})
            if staggered is None:
                plan.unresolved.append(leg.system_id)
                fixed.append(leg)
                continue
            other, hold_km, via, hold, way = staggered
            released.pop(other, None)
            plan.holds[other] = hold_km
            plan.staggered[other] = leg.system_id
            fixed = [o for o in fixed if o.system_id != other] + [hold, way]
            if via is None:
                released[leg.system_id] = course
            else:
                plan.holds[leg.system_id] = via
                plan.detours.append(leg.system_id)
        # a plane holding now flies home once its way is clear of what every other one does;
        # where only planes that stay (circling their homes, holding) are in its way, waiting
        # does not clear it: it detours
        for leg, course in order:
            hold = kept.get(leg.system_id)
            if hold is None:
                continue
            others = [o for o in fixed if o is not hold]
            blocking = [o for o in others if self.conflict(leg, o)]
            if not blocking:
                fixed = [*others, leg]
                continue
            if not all((o.at_home and o.settled) or o.system_id in kept for o in blocking):
                plan.holds[leg.system_id] = keep[leg.system_id]
                continue
            found = self.detour(leg, course, others)
            if found is None:
                plan.unresolved.append(leg.system_id)
                fixed = [*others, leg]
                continue
            plan.holds[leg.system_id], flight = found
            plan.detours.append(leg.system_id)
            fixed = [*others, flight]
        return plan


@dataclass
class ReturnPlan:
    """What :meth:`ReturnSeparation.plan` decided for the planes waiting for their way home."""

    holds: dict[int, np.ndarray] = field(default_factory=dict)  # system id -> point to fly to
    #: of ``holds``, the planes that fly through their point on the way (a detour), not wait
    detours: list[int] = field(default_factory=list)
    unresolved: list[int] = field(default_factory=list)  # conflicting, no hold or detour found
    #: of ``holds``, planes held so that another can leave first (``stagger``): -> that plane
    staggered: dict[int, int] = field(default_factory=dict)


@dataclass(frozen=True)
class HomeCircles:
    """How fast each plane circles its home so that the circles keep d_min
    (:func:`home_circle_speeds`): ``speeds_mps`` for the planes that must fly slower than
    cruise, and the pairs of homes (system ids, km apart) too close even at the slowest."""

    speeds_mps: dict[int, float] = field(default_factory=dict)
    too_close: list[tuple[int, int, float]] = field(default_factory=list)


def home_circle_speeds(
    homes_km: dict[int, np.ndarray], plane: PlaneModel, d_min_km: float
) -> HomeCircles:
    """The airspeed at which each plane circles its home at the end of a mission, so that two
    planes whose homes are close keep d_min there.

    RTL circles home at the loiter radius, r(v) = the tightest turn at airspeed v (or
    WP_LOITER_RAD when wider), and a plane arriving at its home strays up to a loiter
    diameter before it is on its circle (``PlaneModel.loiter_reach_km``). Two homes D apart
    keep d_min while one arrives and the other circles when D >= d_min + 2 r(v) + r(v), so a
    plane flies home at the fastest v <= cruise that meets this for its nearest home, and not
    slower than the autopilot's AIRSPEED_MIN (``PlaneModel.slowest_mps``). Where even that is
    too fast for two planes circling (D < d_min + 2 r), the pair is in ``too_close``: the
    scenario put their homes too near for the airframe (paper-10uav seed 3 at 100 m/s: homes
    2.37 km apart, circles of 1.07 km, 0.70 km between the planes)."""
    ids = sorted(homes_km)
    circles = HomeCircles()
    if len(ids) < 2:
        return circles
    xy = np.array([homes_km[i] for i in ids], dtype=float)
    gap = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(gap, np.inf)
    cruise, slowest = plane.speed_mps, min(plane.slowest_mps, plane.speed_mps)
    # fastest speed whose loiter radius is at most (D - d_min) / 3
    room_km = np.maximum(gap.min(axis=1) - d_min_km, 0.0) / 3.0
    speeds = np.clip(plane.fastest_for_loiter_radius_mps(room_km), slowest, cruise)
    for sid, speed in zip(ids, speeds, strict=True):
        if speed < cruise:
            circles.speeds_mps[sid] = float(speed)
    radius_km = np.array([float(plane.loiter_radius_km(s)) for s in speeds])
    short = gap < d_min_km + radius_km[:, None] + radius_km[None, :]
    for a, b in zip(*np.nonzero(np.triu(short)), strict=True):
        circles.too_close.append((ids[a], ids[b], float(gap[a, b])))
    return circles
