"""The flight home kept d_min apart (mavlink_bridge/return_separation.py), on the geometry alone:
which ways home conflict, who holds, and where."""

from __future__ import annotations

import numpy as np

from mavlink_bridge.flight_prediction import PlaneModel
from mavlink_bridge.return_separation import ReturnSeparation
from mavlink_bridge.safe_return import HomeRoutes
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
