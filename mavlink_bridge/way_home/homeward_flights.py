"""The flights home as the plane model flies them, and when two of them conflict.

Every plane's next stretch home is a :class:`~mavlink_bridge.way_home.homeward.Homeward`: RTL
from where it is as the plane model flies it (``flights_home``), guided to a point and circling
it or through a point and on (``guided_flights``: a hold, a detour), or a straight leg
(``leg``).

Two flights **conflict** when at some instant the planes would be closer than d_min plus what
each may stray from its line: on a straight leg ``slack_km`` on the way (the turn onto the line,
a wider turn than the model) and the circle's reach at the aim (a plane that arrives flying
straight at its loiter point overshoots it by up to a loiter diameter); on a path the plane
model flew, ``track_km`` on the way and its circle once it circles; and never more than it has
flown by then (two planes 2 km apart now, as the mission leaves them, are not a conflict by
themselves). Timing is uncertain (a plane held to cruise may fly slower or faster, commands
arrive late), so a plane at instant t is compared with the other one anywhere in
``t +- (tolerance_s + tolerance_frac * t)``. Two planes both circling their own homes are not
compared: where homes are is the scenario's choice, not the flight home's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from mavlink_bridge.vehicles.flight_prediction import predict_paths, wrap_angle
from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_bridge.way_home.around_threats import HomeRoutes
from mavlink_bridge.way_home.homeward import Homeward

#: ``HomewardFlights.apart_km`` is kept this far beyond the limit: its box corners and the
#: positions it bounds are rounded differently
APART_ROUNDING_KM = 1e-6


@dataclass
class HomewardFlights:
    """Predicts the planes' flights home and judges which of them conflict."""

    routes: HomeRoutes  # the threats, their margin and the plane model
    d_min_km: float  # d_min of C_c
    slack_km: float  # what a plane may stray from its straight line on the way
    tolerance_s: float = 10.0  # timing uncertainty: fixed part ...
    tolerance_frac: float = 0.15  # ... and the part growing with the time ahead
    sample_s: float = 2.0  # instants compared, this far apart (at 100 m/s: 0.2 km)
    #: planes that fly home slower than cruise (``home_circle_speeds``), by system id
    speeds_mps: dict[VehicleKey, float] = field(default_factory=dict)
    #: how far a plane may be from where the plane model flies it (``flights_home``)
    track_km: float = 0.3
    #: a plane whose aim is more than this off its nose may turn about either way (the
    #: simulator's plane, circling clockwise when its RTL came, turned right where the model
    #: turned left, and passed 0.22 km from a plane circling its home: 30 % loss, 20x)
    turns_about_rad: float = 2 * math.pi / 3

    def circle_km(self) -> float:
        """How far a plane strays from the point it circles: its loiter diameter (it arrives
        flying straight at the point, passes it, and only then turns onto its circle)."""
        return float(self.routes.plane.loiter_reach_km())

    def leg(
        self,
        key: VehicleKey,
        xy_km: np.ndarray,
        aim_km: np.ndarray,
        at_home: bool,
        via_km: np.ndarray | None = None,
    ) -> Homeward:
        plane = self.routes.plane
        # RTL home at the home circle's speed; guided (to a hold, through a detour) at cruise,
        # which an autopilot goes back to at each change of mode (ArduPlane)
        home_mps = self.speeds_mps.get(key, plane.speed_mps) if at_home else plane.speed_mps
        travel_mps = home_mps if via_km is None else plane.speed_mps
        return Homeward(
            key,
            np.asarray(xy_km, float),
            np.asarray(aim_km, float),
            travel_mps / 1e3,
            float(plane.loiter_reach_km(home_mps)),
            at_home,
            None if via_km is None else np.asarray(via_km, float),
        )

    def flights_home(
        self, ways: list[tuple[VehicleKey, np.ndarray, np.ndarray, float, float]]
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
        key: VehicleKey,
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
                    key,
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
        on_way, there = self._strays(leg)
        if leg.predicted:
            return np.where(leg.circling(t), there, np.minimum(on_way, flown))
        return np.where(t >= leg.arrival_s, np.minimum(there, flown), np.minimum(on_way, flown))

    def conflict(self, a: Homeward, b: Homeward, margin_km: float = 0.0) -> bool:
        """``clearance_km(a, b) < d_min_km + margin_km``: never where the boxes holding the
        two flights (``apart_km``) are that far apart; else each pair of variants first judged
        at equal instants alone (a subset of the pairs compared: most conflicts show there, at
        a fraction of the cost)."""
        if self.apart_km(a, b) >= self.d_min_km + margin_km + APART_ROUNDING_KM:
            return False
        return any(self._conflict(x, y, margin_km) for x in a.variants for y in b.variants)

    def apart_km(self, a: Homeward, b: Homeward) -> float:
        """A lower bound of ``clearance_km(a, b)``: the distance between the boxes holding
        every place of each flight (``Homeward.extent_km``) less the most each may stray
        (``_stray_km``). Hundreds of planes end a mission far apart from most others: this
        spares the comparison of every pair of instants for nearly every pair of flights (300
        planes: the plan of their flights home took longer than 14 minutes)."""
        (a_lo, a_hi), (b_lo, b_hi) = a.extent_km, b.extent_km
        gap = np.maximum(np.maximum(b_lo - a_hi, a_lo - b_hi), 0.0)
        return float(np.hypot(*gap)) - self._most_stray_km(a) - self._most_stray_km(b)

    def _most_stray_km(self, leg: Homeward) -> float:
        """The most ``_stray_km`` gives ``leg`` or any of its variants, at any instant."""
        return max(max(self._strays(v)) for v in leg.variants)

    def _strays(self, leg: Homeward) -> tuple[float, float]:
        """The most ``leg``'s plane may stray on its way and once there (``_stray_km``)."""
        if leg.predicted:
            return self.track_km, 0.55 * leg.circle_km  # the circle bounds it: no track error
        return self.slack_km, leg.stray_at_aim_km

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

    def closest_km(self, leg: Homeward, others: list[Homeward]) -> float:
        """``min(clearance_km(leg, o) for o in others)`` (inf for none), nearest boxes first
        (``apart_km``): a flight whose box is farther than the closest clearance found so far
        cannot be closer, and is not compared instant by instant."""
        best = math.inf
        for bound, k in sorted((self.apart_km(leg, o), k) for k, o in enumerate(others)):
            if bound - APART_ROUNDING_KM >= best:
                break
            best = min(best, self.clearance_km(leg, others[k]))
        return best

    def guided_flights(
        self,
        key: VehicleKey,
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
        starts = np.repeat(xy[None], len(points), axis=0)
        courses = np.full(len(points), float(course_rad))
        flown = self._flown(starts, courses, points, self._guided_horizon_s(starts, points))
        owner = np.array([k for k, paths in enumerate(flown) for _ in paths])
        paths = [path for paths in flown for path in paths]  # every variant, candidate by candidate
        if then_km is not None:
            paths = self._on_to(paths, points[owner], then_km, radius_km)
        by_point: list[list[np.ndarray]] = [[] for _ in points]
        for k, path in zip(owner, paths, strict=True):
            by_point[k].append(path)
        detour = then_km is not None
        return [
            self._predicted(
                key,
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

    def _guided_horizon_s(self, starts: np.ndarray, aims: np.ndarray) -> float:
        """How long a guided flight is predicted (at cruise): the longest of the straight ways
        from ``starts`` to ``aims``, a half turn onto it and a circle at its end."""
        plane = self.routes.plane
        speed = plane.speed_mps
        radius_km = float(plane.loiter_radius_km(speed))
        turn_s = math.pi / float(plane.turn_rate_radps(speed))
        circle_s = 2 * math.pi * radius_km * 1e3 / speed
        return float(np.hypot(*(aims - starts).T).max()) * 1e3 / speed + turn_s + circle_s

    def _on_to(
        self, paths: list[np.ndarray], points: np.ndarray, then_km: np.ndarray, radius_km: float
    ) -> list[np.ndarray]:
        """Each of ``paths`` (flown to its point of ``points``) leaving its point for
        ``then_km`` once within a loiter radius of it, or at its closest approach, and flown on
        there by the plane model (a detour)."""
        plane = self.routes.plane
        cut = []
        for path, point in zip(paths, points, strict=True):
            dist = np.hypot(*(path - point).T)
            near = dist <= radius_km
            cut.append(int(np.argmax(near)) if near.any() else int(np.argmin(dist)))
        here = np.array([p[i] for p, i in zip(paths, cut, strict=True)])
        before = np.array([p[max(i - 1, 0)] for p, i in zip(paths, cut, strict=True)])
        heading = np.arctan2(*(here - before).T[::-1])
        aims = np.repeat(np.asarray(then_km, float)[None], len(paths), axis=0)
        onward = predict_paths(
            plane, here, heading, aims, self._guided_horizon_s(here, aims), sample_s=self.sample_s,
            dt_s=0.5,
        )  # fmt: skip
        return [
            np.concatenate([p[: i + 1], o[1:]]) for p, i, o in zip(paths, cut, onward, strict=True)
        ]
