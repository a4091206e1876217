"""The flight home kept d_min apart (mavlink_bridge/way_home/kept_apart.py), on the geometry alone:
which ways home conflict, who holds, and where."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mavlink_bridge.vehicles.flight_prediction import PlaneModel
from mavlink_bridge.way_home.around_threats import HomeRoutes
from mavlink_bridge.way_home.home_circles import home_circle_speeds
from mavlink_bridge.way_home.kept_apart import ReturnSeparation
from planner.grid import Grid

THREAT_XY = np.array([[10.0, 10.0]])
THREAT_R = np.array([3.0])


def separation() -> ReturnSeparation:
    routes = HomeRoutes(Grid(30, 30, 1.0), THREAT_XY, THREAT_R, PlaneModel(), margin_km=1.0)
    return ReturnSeparation(routes, 1.0, slack_km=float(routes.plane.loiter_radius_km()))


def test_ways_home_crossing_at_the_same_time_conflict_and_staggered_ones_do_not():
    s = separation()
    a = s.leg(1, np.array([20.0, 20.0]), np.array([26.0, 26.0]), at_home=True)
    # crosses a's line at (23, 23), 4.2 km from both starts: the same instant
    b = s.leg(2, np.array([26.0, 20.0]), np.array([20.0, 26.0]), at_home=True)
    assert s.clearance_km(a, b) < 1.0 and s.clearance_km(b, a) < 1.0
    # the same line 12 km further back: a is home and circling long before b passes
    late = s.leg(2, np.array([32.0, 14.0]), np.array([20.0, 26.0]), at_home=True)
    assert s.clearance_km(a, late) >= 1.0
    # two planes circling their own homes are not compared, however near the homes are
    here = s.leg(1, np.array([2.0, 2.0]), np.array([2.0, 2.0]), at_home=True)
    there = s.leg(2, np.array([3.0, 2.0]), np.array([3.0, 2.0]), at_home=True)
    assert s.clearance_km(here, there) == np.inf


def test_the_later_plane_holds_at_a_safe_point_clear_of_the_other_way():
    s = separation()
    first = s.leg(1, np.array([20.0, 20.0]), np.array([28.0, 28.0]), at_home=True)
    second = s.leg(2, np.array([28.5, 20.0]), np.array([20.0, 28.5]), at_home=True)
    plan = s.plan([], [(first, 0.0), (second, np.pi)])
    assert list(plan.holds) == [2] and plan.unresolved == []  # the nearer home goes first
    point = plan.holds[2]
    hold = s.leg(2, second.start_km, point, at_home=False)
    assert s.clearance_km(hold, first) >= 1.0  # the hold keeps clear of the first's way
    reach = float(PlaneModel().loiter_reach_km())
    assert np.hypot(*(point - THREAT_XY[0])) - THREAT_R[0] >= 1.0 + reach  # and of the threat
    # once the first is home, the second's way is clear
    home = s.leg(1, np.array([28.0, 28.0]), np.array([28.0, 28.0]), at_home=True)
    later = s.leg(2, point, np.array([20.0, 28.5]), at_home=True)
    assert s.plan([home], [(later, 0.0)]).holds == {}


def test_a_plane_circling_its_home_on_anothers_way_is_flown_around_not_waited_for():
    """Plane 1 circles its home, which lies on plane 2's way home: it stays there, so holding
    plane 2 would never clear the conflict (it circled until the watch of the flight home
    ended, 7 minutes at real time), and flying on passed through its circle. Plane 2 detours:
    its way through the detour point keeps d_min from plane 1's circle, and the point is a safe
    place to circle (clear of the threat) if the ground station goes silent."""
    s = separation()
    home_1 = np.array([24.0, 24.0])
    circling = s.leg(1, home_1, home_1, at_home=True)
    way = s.leg(2, np.array([20.0, 20.0]), np.array([28.0, 28.0]), at_home=True)
    assert s.clearance_km(way, circling) < 1.0
    plan = s.plan([circling], [(way, np.pi / 4)])
    assert plan.detours == [2] and plan.unresolved == []
    point = plan.holds[2]
    around = s.leg(2, way.start_km, way.aim_km, at_home=True, via_km=point)
    assert s.clearance_km(around, circling) >= 1.0
    positions = around.positions(np.arange(0.0, around.arrival_s + 1.0, 1.0))
    np.testing.assert_allclose(positions[-1], way.aim_km)  # it does get home
    assert np.hypot(*(positions - home_1).T).min() >= 1.0 + s.circle_km()
    reach = float(PlaneModel().loiter_reach_km())
    assert np.hypot(*(point - THREAT_XY[0])) - THREAT_R[0] >= 1.0 + reach
    # a plane still on its way is waited for (a hold): once it is home the way may clear
    flying = s.leg(1, np.array([28.0, 20.0]), np.array([20.0, 28.0]), at_home=True)
    plan = s.plan([flying], [(way, 0.0)])
    assert list(plan.holds) == [2] and plan.detours == []


def test_planes_whose_homes_are_close_circle_them_slowly_enough_to_keep_d_min():
    """paper-10uav seed 3 starts planes 3 and 4 2.37 km apart: circling their homes at cruise
    (1.07 km circles) they came 0.70 km apart. Each flies home at the fastest speed whose
    circle keeps d_min from the other's while it arrives (overshoot: a loiter diameter), never
    below AIRSPEED_MIN; a far plane keeps cruise; homes too close even then are named."""
    plane = PlaneModel(slowest_mps=60.0)
    homes = {3: np.array([84.5, 55.5]), 4: np.array([86.5, 54.5]), 7: np.array([20.0, 20.0])}
    d = float(np.hypot(*(homes[3] - homes[4])))
    assert d < 1.0 + 2 * float(plane.loiter_radius_km())  # at cruise the circles breach
    circles = home_circle_speeds(homes, plane, 1.0)
    assert set(circles.speeds_mps) == {3, 4} and circles.too_close == []
    for sid in (3, 4):
        speed = circles.speeds_mps[sid]
        assert 60.0 <= speed < plane.speed_mps
        assert 1.0 + 3 * float(plane.loiter_radius_km(speed)) <= d + 1e-9
    # 1.5 km apart: even at AIRSPEED_MIN two circles (0.39 km) leave less than d_min
    close = home_circle_speeds({1: np.zeros(2), 2: np.array([1.5, 0.0])}, plane, 1.0)
    assert close.speeds_mps == {1: 60.0, 2: 60.0}
    assert [(a, b) for a, b, _ in close.too_close] == [(1, 2)]
    # an airframe that cannot fly slower than cruise keeps it: nothing to gain
    assert home_circle_speeds(homes, PlaneModel(), 1.0).speeds_mps == {}


def test_the_flight_home_is_judged_along_the_turn_the_plane_flies():
    """Plane 4 ends its mission 2.4 km south of plane 3's home circle flying west, its own
    home to the east-northeast: the shortest turn home is through north, past plane 3's
    circle (paper-10uav seed 3 at 20 steps: 0.09 km). The plane model's flight home
    (``flights_home``) sees the turn and its way conflicts (so it is not flown as it is: held
    or detoured, ``plan``); heading south, away from plane 3, it is clear by more."""
    plane = PlaneModel(slowest_mps=60.0)
    routes = HomeRoutes(Grid(100, 100, 1.0), np.zeros((0, 2)), np.zeros(0), plane, margin_km=1.0)
    home_3, home_4 = np.array([84.5, 55.5]), np.array([86.5, 54.5])
    speeds = home_circle_speeds({3: home_3, 4: home_4}, plane, 1.0).speeds_mps
    s = ReturnSeparation(routes, 1.0, slack_km=float(plane.loiter_radius_km()), speeds_mps=speeds)
    west, circling = s.flights_home(
        [(4, np.array([84.46, 53.10]), home_4, np.pi, 100.0), (3, home_3, home_3, 0.0, 62.0)]
    )
    assert circling.settled and west.predicted
    # the predicted turn swings north, towards plane 3's home, before heading east
    assert np.hypot(*(west.path_km - home_3).T).min() < 2.0
    assert west.path_km[:, 1].max() > 54.0
    assert s.clearance_km(west, circling) < 1.0
    (south,) = s.flights_home([(4, np.array([84.46, 53.10]), home_4, -np.pi / 2, 100.0)])
    assert s.clearance_km(south, circling) > s.clearance_km(west, circling)


def test_planes_too_close_for_either_to_wait_leave_one_after_the_other():
    """Two planes end the mission 2.5 km apart, plane 2 heading west at plane 1, plane 1
    south, their homes beyond each other: neither can hold or go around the other alone
    (before: ``unresolved``, both flew home and met). Staggered: one holds, the other leaves
    first, as the plane model flies them d_min apart; re-judged as they fly it, the holding
    plane keeps its point and neither is left without a way; a minute later both fly home."""
    s = separation()
    start_1, start_2 = np.array([15.0, 15.0]), np.array([17.5, 15.0])
    home_1, home_2 = np.array([25.0, 25.0]), np.array([5.0, 25.0])
    south, west = 3 * np.pi / 2, np.pi  # the planes' courses
    way_1, way_2 = s.flights_home(
        [(1, start_1, home_1, south, 100.0), (2, start_2, home_2, west, 100.0)]
    )
    assert s.clearance_km(way_1, way_2) < 1.0  # the premise: their ways home conflict
    assert s.hold(way_2, west, [way_1]) is None and s.detour(way_2, west, [way_1]) is None
    plan = s.plan([], [(way_1, south), (way_2, west)])
    assert plan.unresolved == [] and list(plan.staggered.items()) == [(1, 2)]
    hold_km = plan.holds[1]
    (hold,) = s.guided_flights(1, start_1, south, hold_km[None])
    via = plan.holds.get(2)
    if via is None:
        leaving = way_2
    else:
        (leaving,) = s.guided_flights(2, start_2, west, via[None], home_2, at_home=True)
    t = np.arange(0.0, max(hold.arrival_s, leaving.arrival_s) + 60.0, 2.0)
    apart = np.hypot(*(hold.positions(t) - leaving.positions(t)).T)
    assert apart.min() >= 1.0 + 2 * s.track_km, apart.min()  # as the plane model flies them

    def replan(after_s: float):
        k = int(after_s / 2.0)  # the flights are sampled every 2 s
        at = [f.path_km[k] for f in (hold, leaving)]
        courses = [
            float(np.arctan2(*(f.path_km[k] - f.path_km[k - 1])[::-1])) for f in (hold, leaving)
        ]
        ways = s.flights_home(
            [(1, at[0], home_1, courses[0], 100.0), (2, at[1], home_2, courses[1], 100.0)]
        )
        return s.plan(
            [], list(zip(ways, courses, strict=True)), dict(plan.holds), set(plan.detours)
        )

    # re-judged every 2 s as they fly it: plane 1 keeps its point (or flies home), nobody is
    # left unresolved; a minute later both fly home
    for after_s in range(2, 60, 2):
        again = replan(float(after_s))
        assert again.unresolved == [], after_s
        assert 1 not in again.holds or np.allclose(again.holds[1], hold_km), after_s
    assert replan(60.0).holds == {}


def test_a_plane_turning_about_may_turn_either_way_past_a_plane_circling_its_home():
    """At 30 % loss and 20x a plane released from its hold at (26.2, 6.7) km, heading 37 deg,
    its home 11 km to the west-south-west, turned right (it was circling clockwise when its RTL
    took hold) where the model turned left, and passed 0.22 km from a plane circling its
    home at (22.5, 4.5). Judged before: 1.03 km clear of the circle's predicted phase. Now a
    turn about is flown both ways, and a circling plane is anywhere on its circle."""
    plane = PlaneModel()
    routes = HomeRoutes(Grid(30, 30, 1.0), np.zeros((0, 2)), np.zeros(0), plane, margin_km=1.0)
    s = ReturnSeparation(routes, 1.0, slack_km=float(plane.loiter_radius_km()))
    home_2, home_3 = np.array([15.5, 4.5]), np.array([22.5, 4.5])
    leaving, circling = s.flights_home(
        [
            (2, np.array([26.21, 6.72]), home_2, np.radians(37.0), 100.0),
            (3, np.array([22.8, 3.75]), home_3, np.radians(112.0), 100.0),
        ]
    )
    assert circling.settled and circling.alternatives == ()
    (other_way,) = leaving.alternatives  # 154 deg off its nose: both ways round
    # the shorter turn is to the left (north of its position), the other to the right
    assert leaving.path_km[:10, 1].max() > other_way.path_km[:10, 1].max() + 1.0
    assert s.clearance_km(leaving, circling) < 0.0
    # the turn the plane model prefers alone kept clear of the circle's predicted phase
    shorter = replace(leaving, alternatives=())
    assert s.clearance_km(shorter, circling) > s.clearance_km(leaving, circling)


def test_held_planes_circling_within_d_min_of_each_other_are_moved_apart():
    """A late daemon holds: every plane circles its last target, chosen a step apart for a
    step. Planes 1 and 2 circle targets 2.5 km apart (two 1.07 km circles: within d_min of each
    other for part of every lap); plane 3 is far. Plane 1, already on its circle, stays; plane
    2 is moved to a point whose circle, flown by the plane model, keeps d_min from plane 1's
    and the threat margin; plane 3 is left alone."""
    from mavlink_bridge.mission.keeping_up import held_apart

    s = separation()
    on_circle = np.array([20.0, 20.0]) + np.array([0.0, float(s.routes.plane.loiter_radius_km())])
    planes = [
        (1, on_circle, 0.0, np.array([20.0, 20.0])),  # on its circle, flying east (clockwise)
        (2, np.array([24.5, 22.0]), np.pi, np.array([22.5, 20.0])),
        (3, np.array([4.0, 25.0]), 0.0, np.array([4.0, 26.0])),
    ]
    flights = {sid: s.guided_flights(sid, xy, c, aim[None])[0] for sid, xy, c, aim in planes}
    assert s.conflict(flights[1], flights[2])  # the premise: their circles come within d_min
    moves, stuck = held_apart(s, planes)
    assert stuck == [] and list(moves) == [2]
    (moved,) = s.guided_flights(2, planes[1][1], np.pi, moves[2][None])
    assert not s.conflict(moved, flights[1]) and not s.conflict(moved, flights[3])
    n = min(len(moved.path_km), len(flights[1].path_km))  # as the plane model flies them
    assert np.hypot(*(moved.path_km[:n] - flights[1].path_km[:n]).T).min() >= 1.0
    reach = float(PlaneModel().loiter_reach_km())
    assert np.hypot(*(moves[2] - THREAT_XY[0])) - THREAT_R[0] >= 1.0 + reach


def test_a_plane_in_rtl_may_hold_off_its_home_for_another_to_pass():
    """Plane 2 is 2.6 km from plane 3's home, where plane 3 circles, and its way home runs
    through that circle: too close to hold or to go round alone, it flew on with a warning and
    passed 0.01 km from plane 3 (10 % loss, 5x). A plane in RTL can still be guided: plane 3
    holds off its home while plane 2 goes round it, both as the plane model flies them."""
    s = separation()
    home_2, home_3 = np.array([15.5, 24.5]), np.array([22.5, 24.5])
    circling, way = s.flights_home(
        [(3, home_3 - np.array([0.0, 1.07]), home_3, 0.0, 100.0),
         (2, np.array([25.0, 25.5]), home_2, np.pi, 100.0)]
    )  # fmt: skip
    assert circling.settled and s.conflict(way, circling)
    assert s.plan([circling], [(way, np.pi)]).unresolved == [2]  # not movable: no way
    plan = s.plan([circling], [(way, np.pi)], movable={3: 0.0})
    assert plan.unresolved == [] and plan.staggered == {3: 2}
    (held,) = s.guided_flights(3, circling.start_km, 0.0, plan.holds[3][None])
    if 2 in plan.holds:
        (gone,) = s.guided_flights(2, way.start_km, np.pi, plan.holds[2][None], home_2, True)
    else:
        gone = way
    assert not s.conflict(gone, held)


def test_on_a_small_area_a_plane_with_no_clear_way_home_takes_the_one_that_keeps_farthest():
    """px4-3uav (0.4 km cells, 4 x 3.2 km, PX4's 12 m/s SIH plane, d_min 0.6) searching to
    its last step, seed 3 in the simulator: plane 3 ended beside plane 1's home, its own home
    beyond plane 2's. Plane 1 comes home from the north, plane 2 circles its home: every way
    of plane 3 starts too near plane 1 to keep d_min for sure. It flew its straight line on
    and passed 0.04 km from plane 2 circling; the hold and detour points, rings fixed in km
    for the 100 m/s plane (2 to 12 km), were all off the area. Rings in ``pass_km`` and the
    way that keeps farthest: plane 3 holds or goes round, never through plane 2's circle."""
    plane = PlaneModel(
        speed_mps=12.0, bank_limit_deg=50.0, capture_radius_m=30.0, wp_loiter_radius_m=80.0,
        min_speed_mps=12.0, max_speed_mps=13.5, slowest_mps=10.0,
    )  # fmt: skip
    routes = HomeRoutes(
        Grid(10, 8, 0.4), np.array([[2.2, 2.2]]), np.array([0.25]), plane, margin_km=0.3
    )
    s = ReturnSeparation(routes, 0.6, slack_km=float(plane.loiter_radius_km()))
    assert s.pass_km() < 1.0  # the rings fit the area: 0.5 to 3 of it
    home_1, home_2, home_3 = np.array([0.6, 0.6]), np.array([2.2, 0.6]), np.array([3.4, 0.6])
    coming, circling, way = s.flights_home(
        [(1, np.array([0.59, 1.18]), home_1, -np.pi / 2, 12.0),
         (2, home_2 - np.array([0.0, 0.08]), home_2, 0.0, 12.0),
         (3, np.array([1.09, 0.58]), home_3, 0.0, 12.0)]
    )  # fmt: skip
    assert s.conflict(way, circling) and s.conflict(way, coming)
    plan = s.plan([coming, circling], [(way, 0.0)])
    assert plan.unresolved == [3] and 3 in plan.holds  # a hold or a detour, not the line
    point = plan.holds[3]
    then = home_3 if 3 in plan.detours else None
    (taken,) = s.guided_flights(3, way.start_km, 0.0, point[None], then, then is not None)
    closest = min(s.clearance_km(taken, coming), s.clearance_km(taken, circling))
    assert closest == pytest.approx(plan.closest_km[3])
    # the line passes through plane 2's circle; the way taken keeps clear of it
    assert s.clearance_km(way, circling) < 0 < s.clearance_km(taken, circling)
    assert closest > min(s.clearance_km(way, coming), s.clearance_km(way, circling))


def crowd(n: int, seed: int) -> tuple[ReturnSeparation, list[tuple[object, float]]]:
    """``n`` planes ending a mission anywhere in a 100 km square (threats as paper-20uav's
    first three), each 0-20 km from its home on any course: their flights home as the plane
    model flies them."""
    rng = np.random.default_rng(seed)
    plane = PlaneModel()
    threats, radii = np.array([[30.0, 70.0], [60.0, 40.0], [80.0, 80.0]]), np.full(3, 5.0)
    routes = HomeRoutes(Grid(100, 100, 1.0), threats, radii, plane, margin_km=1.0)
    s = ReturnSeparation(routes, 1.0, slack_km=float(plane.loiter_radius_km()))
    homes = rng.uniform(4.0, 96.0, (n, 2))
    xy = np.clip(homes + rng.uniform(-20.0, 20.0, (n, 2)), 1.0, 99.0)
    courses = rng.uniform(-np.pi, np.pi, n)
    ways = [(k + 1, xy[k], homes[k], courses[k], plane.speed_mps) for k in range(n)]
    return s, list(zip(s.flights_home(ways), courses, strict=True))


def test_flights_whose_boxes_are_apart_are_clear_whenever_they_fly():
    """``apart_km`` bounds ``clearance_km`` from below for every kind of flight (RTL as the
    plane model flies it, a guided hold, a detour, a straight leg), so the pairs it spares
    are clear: the plan is the same as with every pair of instants compared."""
    s, waiting = crowd(12, seed=3)
    flights = [leg for leg, _ in waiting]
    spared = [s.apart_km(a, b) > 1.0 for a in flights for b in flights]
    assert sum(spared) > len(spared) / 2  # most pairs of the crowd
    leg, course = waiting[0]
    holds = s._hold_points(leg.start_km, course)[::8]
    flights += s.guided_flights(leg.key, leg.start_km, course, holds)
    flights += s.guided_flights(
        leg.key, leg.start_km, course, np.array([[50.0, 50.0]]), leg.aim_km, at_home=True
    )
    flights.append(s.leg(99, np.array([40.0, 10.0]), np.array([45.0, 12.0]), True))
    flights.append(s.leg(98, np.array([5.0, 5.0]), np.array([9.0, 5.0]), False, np.array([7, 8])))
    bounds = [(s.apart_km(a, b), s.clearance_km(a, b)) for a in flights for b in flights]
    assert all(bound <= clearance + 1e-9 for bound, clearance in bounds)


def test_a_crowd_is_planned_home_as_without_the_spared_comparisons():
    class EveryPair(ReturnSeparation):
        def apart_km(self, a, b) -> float:
            return -np.inf

    s, waiting = crowd(30, seed=1)
    plan = s.plan([], waiting)
    every = EveryPair(**{f: getattr(s, f) for f in s.__dataclass_fields__}).plan([], waiting)
    assert plan.holds.keys() == every.holds.keys() and plan.holds  # (someone holds)
    assert all(np.array_equal(plan.holds[k], every.holds[k]) for k in plan.holds)
    assert plan.detours == every.detours and plan.unresolved == every.unresolved
    assert plan.staggered == every.staggered
