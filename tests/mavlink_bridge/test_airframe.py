"""The airframe read at launch (mavlink_bridge/vehicles/airframe.py): parameters answered by the
vehicle become its limits (ArduPlane's names, older names, PX4's), the fleet flies the most
restrictive of them, and a scenario the airframe cannot fly is said with its fix. The read
itself against real ArduPlane SITL is in tests/sitl/test_sitl_mission.py."""

from __future__ import annotations

import math

import numpy as np

from mavlink_bridge.vehicles.airframe import (
    MAX_SEPARATION_MARGIN_KM,
    MAX_THREAT_MARGIN_KM,
    airframe_from_params,
    fleet_plane_model,
    scenario_warnings,
    separation_margin_km,
    threat_margin_km,
)
from mavlink_bridge.vehicles.flight_prediction import leg_speed_mps, predict_paths
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_wire.protocol import mavlink
from planner.scenario import load_scenario

ARDUPLANE = {  # ArduPlane SITL's defaults (../shared/sitl/README.md)
    "AIRSPEED_MIN": 10.0, "AIRSPEED_CRUISE": 22.0, "AIRSPEED_MAX": 30.0,
    "ROLL_LIMIT_DEG": 65.0, "WP_LOITER_RAD": 80.0, "WP_RADIUS": 90.0,
}  # fmt: skip


def vehicle(sysid: int, params: dict[str, float], autopilot: int | None = None) -> VehicleState:
    v = VehicleState(sysid, link=None)  # type: ignore[arg-type]
    v.params.update(params)
    if autopilot is not None:
        v.autopilot = autopilot
    return v


def test_arduplane_names_old_names_and_px4_names_are_read():
    cfg = load_scenario("arduplane-3uav").config
    new = airframe_from_params(vehicle(1, ARDUPLANE), cfg)
    assert (new.min_airspeed_mps, new.cruise_mps, new.max_airspeed_mps) == (10, 22, 30)
    assert (new.bank_limit_deg, new.wp_loiter_radius_m) == (65, 80) and not new.defaulted
    turn_m = 22.0**2 / (9.80665 * math.tan(math.radians(65)))  # v^2 / (g tan(bank))
    assert math.isclose(new.min_turn_radius_m(22.0), turn_m)
    old = airframe_from_params(
        vehicle(2, {"ARSPD_FBW_MIN": 12, "TRIM_ARSPD_CM": 2000, "ARSPD_FBW_MAX": 28,
                    "LIM_ROLL_CD": 4500, "WP_LOITER_RAD": -60}), cfg,
    )  # fmt: skip
    assert (old.min_airspeed_mps, old.cruise_mps, old.max_airspeed_mps) == (12, 20, 28)
    assert old.bank_limit_deg == 45 and old.wp_loiter_radius_m == 60  # < 0: counter-clockwise
    assert old.defaulted == ("WP_RADIUS",)
    px4 = airframe_from_params(
        vehicle(3, {"FW_AIRSPD_MIN": 11, "FW_AIRSPD_TRIM": 16, "FW_AIRSPD_MAX": 25, "FW_R_LIM": 50,
                    "NAV_LOITER_RAD": 70, "NAV_ACC_RAD": 30}, mavlink.MAV_AUTOPILOT_PX4), cfg,
    )  # fmt: skip
    assert (px4.cruise_mps, px4.bank_limit_deg, px4.wp_loiter_radius_m) == (16, 50, 70)
    # nothing answered: the daemon's assumption, and it says which names were not reported
    silent = airframe_from_params(vehicle(4, {}), cfg)
    assert silent.cruise_mps == cfg.speed_mps and "AIRSPEED_MIN" in silent.describe()


def test_the_fleet_flies_the_most_restrictive_airframe():
    cfg = load_scenario("arduplane-3uav").config
    a = airframe_from_params(vehicle(1, ARDUPLANE), cfg)
    b = airframe_from_params(vehicle(2, {**ARDUPLANE, "ROLL_LIMIT_DEG": 45, "AIRSPEED_MAX": 27,
                                         "WP_LOITER_RAD": 120}), cfg)  # fmt: skip
    model = fleet_plane_model([a, b], cfg)
    assert model.bank_limit_deg == 45 and model.wp_loiter_radius_m == 120
    assert (model.min_speed_mps, model.max_speed_mps) == (22, 27)  # v .. min(1.5 v, slowest max)
    # the loiter circle is WP_LOITER_RAD (wider than the tightest turn at 22 m/s and 45 deg)
    assert math.isclose(float(model.loiter_radius_km(22.0)), 0.12)


def test_a_scenario_the_airframe_cannot_fly_gets_a_warning_with_the_fix():
    arduplane = load_scenario("arduplane-3uav").config
    frame = airframe_from_params(vehicle(1, ARDUPLANE), arduplane)
    assert scenario_warnings([frame], arduplane) == []
    paper = load_scenario("paper-10uav").config  # 100 m/s, 1 km cells, 10 s steps
    (line,) = scenario_warnings([frame], paper)
    assert "vehicle 1 flies 10..30 m/s but the scenario's UAV speed is 100 m/s" in line
    assert "speed_mps = 22" in line and "step_s = 45" in line
    fast = arduplane.replace(step_s=40.0)  # a diagonal cell needs 35 m/s
    (line,) = scenario_warnings([frame], fast)
    assert "cannot fly a diagonal cell of 1 km in one 40 s step" in line and "step_s >= 48" in line


def test_the_threat_and_separation_margins_follow_the_airframe():
    """A plane that circles within 80 m is not kept 1 km off the threat zones (three ArduPlane
    SITL planes were held beside arduplane-3uav's zones for most of a mission); the simulator's
    100 m/s plane keeps its 1 km."""
    arduplane = load_scenario("arduplane-3uav").config
    small = fleet_plane_model([airframe_from_params(vehicle(1, ARDUPLANE), arduplane)], arduplane)
    assert math.isclose(threat_margin_km(small, 0.25), 0.08 + 0.25)
    paper = load_scenario("paper-10uav").config
    sim = {**ARDUPLANE, "AIRSPEED_MIN": 60, "AIRSPEED_CRUISE": 100, "AIRSPEED_MAX": 150,
           "ROLL_LIMIT_DEG": 45, "WP_LOITER_RAD": 60}  # fmt: skip
    big = fleet_plane_model([airframe_from_params(vehicle(1, sim), paper)], paper)
    assert threat_margin_km(big, 0.25) == MAX_THREAT_MARGIN_KM == 1.0
    # the separation margin too: two 80 m circles and the predicted 0.3 km, where 1 km on top of
    # px4-3uav's d_min (0.6 km) pushed three PX4 planes into its corners; the simulator's 1 km
    assert math.isclose(separation_margin_km(small, 0.3), 2 * 0.08 + 0.3)
    assert separation_margin_km(big, 0.3) == MAX_SEPARATION_MARGIN_KM == 1.0


PX4_SIH = {  # PX4 SITL's SIH airplane (airframe 10041) as it answers (benchmarks/px4_sih_flight.py)
    "FW_AIRSPD_MIN": 10.0, "FW_AIRSPD_TRIM": 15.0, "FW_AIRSPD_MAX": 20.0, "FW_R_LIM": 50.0,
    "NAV_LOITER_RAD": 80.0, "NAV_ACC_RAD": 10.0, "SYS_AUTOSTART": 10041,
}  # fmt: skip


def test_px4_sih_airplane_is_capped_to_the_speed_it_really_flies():
    cfg = load_scenario("arduplane-3uav").config.replace(speed_mps=12.0)
    sih = airframe_from_params(vehicle(1, PX4_SIH, mavlink.MAV_AUTOPILOT_PX4), cfg)
    # it reports 15 / 20 m/s but tops out at 13.6 m/s at full throttle
    assert (sih.min_airspeed_mps, sih.cruise_mps, sih.max_airspeed_mps) == (10, 13.5, 13.5)
    assert "FW_AIRSPD_MAX 20 capped to 13.5 m/s" in sih.describe()
    # another PX4 airframe is believed, and ArduPilot is never capped
    other = {**PX4_SIH, "SYS_AUTOSTART": 2100}
    believed = airframe_from_params(vehicle(2, other, mavlink.MAV_AUTOPILOT_PX4), cfg)
    assert (believed.cruise_mps, believed.max_airspeed_mps, believed.capped) == (15, 20, "")
    ardu = airframe_from_params(vehicle(3, {**ARDUPLANE, "SYS_AUTOSTART": 10041}), cfg)
    assert ardu.max_airspeed_mps == 30 and ardu.capped == ""


def test_a_mixed_fleet_times_each_planes_legs_within_its_own_airspeed_range():
    cfg = load_scenario("arduplane-3uav").config.replace(speed_mps=12.0)
    ardu = airframe_from_params(vehicle(1, ARDUPLANE), cfg)
    sih = airframe_from_params(vehicle(2, PX4_SIH, mavlink.MAV_AUTOPILOT_PX4), cfg)
    model = fleet_plane_model([ardu, sih], cfg)
    assert model.uav_speed_ranges_mps == ((12, 18), (12, 13.5))  # v .. min(1.5 v, own max)
    assert model.bank_limit_deg == 50  # the margins are judged as the most restrictive plane
    # a long leg behind the clock: each plane catches up at its own fastest
    here, there = np.zeros((2, 2)), np.array([[2.0, 0.0], [2.0, 0.0]])
    speeds = leg_speed_mps(model, here, here, there, np.array([12.0, 12.0]), 60.0, np.arange(2))
    assert list(speeds) == [18, 13.5]
    assert model.fastest_leg_mps == 18  # the envelope's escape time is the fastest plane's
    # --airspeed-range given: every plane's range
    forced = fleet_plane_model([ardu, sih], cfg, airspeed_range_mps=(11.0, 13.0))
    assert forced.uav_speed_ranges_mps == ((11, 13), (11, 13))


def test_a_mixed_fleet_predicts_each_plane_on_its_own_turn():
    """ArduPlane (65 deg of bank, WP_RADIUS 90 m) beside the SIH plane (50 deg, NAV_ACC_RAD 10
    m): the flight envelope predicts each plane's path with its own turn, not every plane as
    the widest-turning one; a fleet of one airframe keeps the one model."""
    cfg = load_scenario("arduplane-3uav").config.replace(speed_mps=22.0)
    ardu = airframe_from_params(vehicle(1, ARDUPLANE), cfg)
    sih = airframe_from_params(vehicle(2, PX4_SIH, mavlink.MAV_AUTOPILOT_PX4), cfg)
    model = fleet_plane_model([ardu, sih], cfg)
    assert model.uav_turn_limits == ((65, 80, 90), (50, 80, 10))
    rows = model.rows(np.array([0, 1, 0]))
    assert list(rows.bank_limit_deg) == [65, 50, 65] and list(rows.capture_radius_m) == [90, 10, 90]
    assert fleet_plane_model([ardu, ardu], cfg).rows(np.array([0, 1])) == fleet_plane_model(
        [ardu, ardu], cfg
    )
    # both sent back the way they came, at 22 m/s: the ArduPlane turns about on a tighter
    # circle than the fleet's 50 deg model would fly it; the SIH plane as that model
    start, course, aim = np.zeros((2, 2)), np.zeros(2), np.array([[-2.0, 0.0], [-2.0, 0.0]])
    own = predict_paths(model.rows(np.array([0, 1])), start, course, aim, 20.0)
    fleet = predict_paths(model, start, course, aim, 20.0)
    own_width, fleet_width = (np.abs(p[:, :, 1]).max(axis=1) for p in (own, fleet))
    assert own_width[0] < 0.8 * fleet_width[0]
    np.testing.assert_allclose(own_width[1], fleet_width[1])
