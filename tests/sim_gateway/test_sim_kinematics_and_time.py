"""Fixed-wing kinematics, the look encoding, determinism of fast runs, command-line errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from loopback import run_swarmplan

from mavlink_bridge.vehicles.flight_prediction import PlaneModel, predict_paths
from mavlink_wire.looks import FILE_URL_CHARS, look_urls, parse_look_url
from planner.scenario import load_scenario
from sim_gateway.fixed_wing import ORBIT, FleetKinematics
from sim_gateway.simulator import SimOptions, Simulator, SimulatorError


def _plane(**kw) -> FleetKinematics:
    fleet = FleetKinematics(np.array([0.0]), np.array([0.0]), np.array([0.0]), **kw)
    fleet.airborne[:] = True
    return fleet


def test_turn_rate_allows_45_degrees_per_decision_step():
    fleet = _plane()
    fleet.orbit(0, 5000.0, 0.0, 1.0)  # hard turn to the right, as tight as it can
    for _ in range(100):
        fleet.step(0.1)
    turned = math.degrees(fleet.course_rad[0])
    assert 45.0 <= turned <= 60.0
    assert fleet.min_turn_radius_m()[0] == pytest.approx(100.0**2 / 9.80665, rel=1e-6)


def test_pursuit_arrives_then_orbits_at_a_flyable_radius():
    fleet = _plane()
    fleet.fly_to(0, 0.0, 8000.0, 90.0, 100.0)
    arrived_at = None
    for k in range(3000):
        if fleet.step(0.1).arrived[0] and arrived_at is None:
            arrived_at = k
    assert arrived_at is not None and 780 <= arrived_at <= 800  # 8 km at 100 m/s: 80 s
    assert fleet.guidance[0] == ORBIT
    d = math.hypot(fleet.x_m[0], fleet.y_m[0] - 8000.0)
    assert d == pytest.approx(fleet.effective_orbit_radius_m()[0], rel=0.05)


def test_altitude_follows_its_target_at_the_climb_limit():
    fleet = _plane(climb_mps=5.0)
    fleet.target_alt_m[:] = 100.0
    for _ in range(100):
        fleet.step(0.1)
    assert fleet.alt_m[0] == pytest.approx(50.0)
    assert fleet.distance_flown_m[0] == pytest.approx(1000.0)


def test_look_urls_split_at_205_chars_and_round_trip():
    offsets = [(dx, dy) for dx in range(-30, 30) for dy in (-17, 23)]
    urls = look_urls(offsets)
    assert len(urls) > 1 and all(len(u) <= FILE_URL_CHARS for u in urls)
    assert urls[0].startswith("look:") and all(u.startswith("look+:") for u in urls[1:])
    assert [o for u in urls for o in parse_look_url(u)] == offsets
    assert look_urls([]) == ["look:"]
    assert look_urls([(0, 1), (-2, 0)]) == ["look:0,1;-2,0"]


def _fast_run(seed: int) -> tuple[np.ndarray, np.ndarray, int]:
    options = SimOptions(seed=seed, fast=True, airborne=True, gcs_port=9)  # discard port
    with Simulator(load_scenario("paper-10uav"), options) as sim:
        sim.run(sim_duration_s=300.0)
        return np.stack([sim.fleet.x_m, sim.fleet.y_m]), sim.world.positions.copy(), sim.looks_sent


def test_fast_runs_are_deterministic_for_a_seed():
    a, b, c = _fast_run(4), _fast_run(4), _fast_run(5)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and a[2] == b[2] == 300
    assert not np.array_equal(a[1], c[1])


def test_bad_options_raise_one_clear_error():
    with pytest.raises(SimulatorError, match="--speedup"):
        SimOptions(speedup=-1).validate()
    with pytest.raises(SimulatorError, match="--vehicles"):
        SimOptions(vehicles=500).validate()


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--scenario", "no-such-scenario"], "no-such-scenario"),
        (["--speedup", "-3"], "--speedup"),
        (["--vehicles", "0"], "--vehicles"),
        (["--gcs-port", "70000"], "--gcs-port"),
        (["--scenario", "paper-2uav", "--vehicles", "5"], "fixes 2 UAV starts"),
    ],
)
def test_command_line_errors_are_one_line_without_traceback(argv, needle):
    proc = run_swarmplan(["sim", *argv, "--duration-s", "1"], timeout=60)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert any(needle in line for line in lines), proc.stderr


@pytest.mark.parametrize("speed_mps", [100.0, 140.0, 75.0])
def test_daemon_flight_prediction_is_the_simulated_flight(speed_mps):
    """The daemon's model of a plane (mavlink_bridge.vehicles.flight_prediction) and the simulator's
    kinematics agree: sent to a point behind its left wing at a new airspeed, the simulated
    plane turns, speeds up or slows down, arrives and circles where the daemon predicted. A
    constant changed on one side only (bank limit, loiter size, acceleration) shows here."""
    fleet = _plane()
    aim_m = (-2500.0, 1500.0)
    fleet.fly_to(0, *aim_m, capture_radius_m=90.0, then_orbit_radius_m=60.0)
    fleet.set_airspeed(0, speed_mps)
    flown = [(0.0, 0.0)]
    for k in range(120 * 5):
        fleet.step(0.2)
        if (k + 1) % 5 == 0:
            flown.append((fleet.x_m[0] / 1e3, fleet.y_m[0] / 1e3))
    predicted = predict_paths(
        PlaneModel(),
        np.zeros((1, 2)),
        np.array([math.pi / 2]),  # north, counter-clockwise from east
        np.array([aim_m]) / 1e3,
        horizon_s=120.0,
        commanded_mps=np.array([speed_mps]),
    )[0]
    gap_km = np.hypot(*(predicted - np.array(flown)).T)
    assert gap_km.max() < 0.02, gap_km.max()
    # it did circle: the last 15 s on the loiter circle flown at that airspeed
    radius = np.hypot(*(np.array(flown[-15:]) - np.array(aim_m) / 1e3).T)
    loiter = PlaneModel().loiter_radius_km(speed_mps)
    assert np.all(np.abs(radius - loiter) < 0.1 * loiter)
