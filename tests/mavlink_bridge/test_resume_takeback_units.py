"""A resumed daemon's judgement of one plane in the air (mavlink_bridge/resume_takeback.py), on
the geometry and the range account alone: continue when it is clear of the threats, in the
area and has the range for the safe way home plus the reserve; home otherwise, saying why.
(The whole resume, with real processes, is tests/reliability/test_resume_takeback.py.)"""

from __future__ import annotations

import math

import numpy as np

from mavlink_bridge.flight_prediction import PlaneModel
from mavlink_bridge.protocol import PLANE_MODE_RTL, mavlink
from mavlink_bridge.resume_takeback import (
    CONTINUE,
    HOME,
    RangeAccount,
    TakeBackJudge,
    range_account,
)
from mavlink_bridge.safe_return import HomeRoutes
from mavlink_bridge.vehicle_state import VehicleState
from planner.grid import Grid

HOME_KM = np.array([5.5, 5.5])


def judge(max_range_km: float = 100.0) -> TakeBackJudge:
    routes = HomeRoutes(
        Grid(40, 40, 1.0), np.array([[20.0, 20.0]]), np.array([5.0]), PlaneModel(), margin_km=1.0
    )
    return TakeBackJudge(routes, (40.0, 40.0), 0.5, max_range_km, reserve_km=4.0)


def plane(battery_pct: int = -1) -> VehicleState:
    v = VehicleState(system_id=2, link=None)  # type: ignore[arg-type]
    v.base_mode = mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    v.custom_mode = PLANE_MODE_RTL
    v.system_status = mavlink.MAV_STATE_CRITICAL
    v.battery_pct = battery_pct
    return v


def flown(km: float) -> RangeAccount:
    return RangeAccount(at_checkpoint_km=km, outage_km=0.0, battery_used_km=None)


def test_range_decides_by_the_safe_way_home_not_the_distance_flown_alone():
    j = judge(max_range_km=60.0)
    near = j.judge(plane(), np.array([8.0, 8.0]), HOME_KM, flown(50.0))
    assert near.decision == CONTINUE and near.mode == "RTL" and near.status == "CRITICAL"
    far = j.judge(plane(), np.array([35.0, 8.0]), HOME_KM, flown(50.0))
    assert far.decision == HOME and "range spent" in far.why, far.why
    assert far.way_home_km is not None and far.way_home_km > 6.0  # 29.5 km, beyond the 10 left
    # the way home around the threat is longer than the straight line through it
    behind = np.array([34.0, 34.0])
    way = j.routes.way_length_km(behind, HOME_KM)
    assert way > float(np.hypot(*(behind - HOME_KM))) + 0.5 and math.isfinite(way)


def test_inside_a_threat_or_outside_the_area_goes_home_whatever_the_range():
    j = judge()
    inside = j.judge(plane(), np.array([21.0, 19.0]), HOME_KM, flown(0.0))
    assert inside.decision == HOME and "threats[0]" in inside.why, inside.why
    out = j.judge(plane(), np.array([41.5, 10.0]), HOME_KM, flown(0.0))
    assert out.decision == HOME and "outside" in out.why, out.why
    assert "outside" not in j.judge(plane(), np.array([40.3, 10.0]), HOME_KM, flown(0.0)).why


def test_the_range_account_takes_the_outage_and_the_battery_whichever_says_more():
    v = plane(battery_pct=20)  # 80 % of L_max used
    account = range_account(v, at_checkpoint_km=10.0, outage_s=100.0, cruise_mps=100.0,
                            max_range_km=50.0)  # fmt: skip
    assert account.outage_km == 10.0 and account.battery_used_km == 40.0
    assert account.flown_km == 40.0
    assert range_account(plane(), 10.0, 100.0, 100.0, 50.0).flown_km == 20.0  # no battery
    j = judge(max_range_km=50.0)
    assert j.judge(v, np.array([8.0, 8.0]), HOME_KM, account).decision == CONTINUE  # 10 left
    v.battery_pct = 10  # 5 km left: not enough for the 3.5 km way home + 4 km reserve
    spent = range_account(v, 10.0, 100.0, 100.0, 50.0)
    home = j.judge(v, np.array([8.0, 8.0]), HOME_KM, spent)
    assert home.decision == HOME and "battery: 45 km used" in home.why, home.why
