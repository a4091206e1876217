"""The way home around threats (mavlink_bridge/way_home/around_threats.py), on the geometry alone:
RTL only where the straight line home and the turn onto it keep the margin; otherwise a waypoint
that is a safe place to circle, reached by a leg and a turn that keep it too."""

from __future__ import annotations

import math

import numpy as np

from mavlink_bridge.vehicles.flight_prediction import PlaneModel, predict_paths
from mavlink_bridge.way_home.around_threats import HomeRoutes
from planner.constraints import segment_clearance
from planner.grid import Grid

THREAT_XY = np.array([[10.0, 10.0]])
THREAT_R = np.array([3.0])


def routes() -> HomeRoutes:
    return HomeRoutes(Grid(20, 20, 1.0), THREAT_XY, THREAT_R, PlaneModel(), margin_km=1.0,
                      turn_margin_km=1.0)  # fmt: skip


def test_a_threat_between_plane_and_home_is_flown_around_by_safe_waypoints():
    r = routes()
    home = np.array([10.5, 3.5])
    xy, course = np.array([10.5, 17.5]), -math.pi / 2  # due south, at the threat
    assert not r.rtl_clear(xy, course, home)
    loiter = float(r.plane.loiter_radius_km())
    legs = 0
    while (w := r.waypoint(xy, home, course)) is not None:
        legs += 1
        assert legs < 10
        leg = segment_clearance(xy, w, THREAT_XY, THREAT_R)
        assert leg >= 1.0  # the leg keeps the margin ...
        assert np.hypot(*(w - THREAT_XY[0])) - THREAT_R[0] >= 1.0 + 2 * loiter  # ... its circle
        course = math.atan2(w[1] - xy[1], w[0] - xy[0])
        xy = w
    assert legs >= 1 and r.rtl_clear(xy, course, home)


def test_a_clear_line_home_with_a_turn_into_a_threat_is_no_rtl():
    """A plane 1.8 km from a threat's edge, heading at it, home behind it: the line home keeps the
    margin, the turn onto it would not (the flaw a 0.25 km turn margin let through): no RTL, a
    waypoint whose turn keeps at least as much."""
    r = routes()
    xy, course, home = np.array([14.8, 10.0]), math.pi, np.array([19.0, 2.0])
    turn_s = math.pi / float(r.plane.turn_rate_radps())

    def turn_clearance(aim: np.ndarray) -> float:
        path = predict_paths(r.plane, xy[None], np.array([course]), aim[None], turn_s)[0]
        return float((np.hypot(*(path - THREAT_XY[0]).T) - THREAT_R[0]).min())

    assert r.line_clear(xy, home) and turn_clearance(home) < 1.0
    assert not r.rtl_clear(xy, course, home)
    w = r.waypoint(xy, home, course)  # no turn keeps 1 km this near: the one that keeps most
    assert w is not None and turn_clearance(w) >= turn_clearance(home) > 0


def test_no_threat_in_the_way_is_plain_rtl():
    r = routes()
    assert r.rtl_clear(np.array([3.0, 3.0]), 0.0, np.array([1.5, 1.5]))
    assert r.waypoint(np.array([3.0, 3.0]), np.array([1.5, 1.5]), 0.0) is None
