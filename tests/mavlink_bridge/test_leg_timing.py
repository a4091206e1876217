"""Leg timing: the daemon asks each plane for the airspeed that flies its leg in one decision
step, so the planes keep the paper's grid clock (a diagonal cell, 1.41 km, per 10 s step)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_daemon_protocol import options

from mavlink_bridge.mission.daemon import MissionDaemon
from mavlink_bridge.vehicles.flight_prediction import PlaneModel, leg_speed_mps, predict_paths
from mavlink_wire.protocol import mavlink
from planner.grid import HEADING_STEPS, Grid

STEP_S = 10.0


def fly_legs(headings: list[int], timed: bool) -> np.ndarray:
    """Fly a plane cell to cell along ``headings`` with the daemon's own model (guided target one
    leg beyond the next centre, as the daemon sends it); the distance (km) from the planned
    cell centre at every decision instant."""
    model, grid = PlaneModel(), Grid(100, 100, 1.0)
    cell = np.array([20, 20])
    position = grid.centre_km(cell)
    course, speed = math.radians(45 * headings[0]), model.speed_mps
    lags = []
    for h in headings:
        nxt = cell + HEADING_STEPS[h]
        a, b = grid.centre_km(cell), grid.centre_km(nxt)
        command = model.speed_mps
        if timed:
            command = float(leg_speed_mps(model, position, a, b, speed, STEP_S)[0])
        path = predict_paths(
            model, position, np.array([course]), b + (b - a), STEP_S,
            speed_mps=np.array([speed]), commanded_mps=np.array([command]),
        )[0]  # fmt: skip
        course = math.atan2(*(path[-1] - path[-2])[::-1])
        speed += float(
            np.clip(command - speed, -model.accel_mps2 * STEP_S, model.accel_mps2 * STEP_S)
        )
        position, cell = path[-1], nxt
        lags.append(float(np.hypot(*(position - b))))
    return np.array(lags)


def test_timed_legs_keep_the_grid_clock_where_cruise_speed_falls_behind():
    # a search pattern of diagonal runs and 45 degree turns (the planner's phi_max)
    headings = [0, 1, 1, 1, 1, 1, 2, 1, 1, 1, 0, 1, 1, 1, 1, 1]
    timed = fly_legs(headings, timed=True)
    cruise = fly_legs(headings, timed=False)
    assert cruise[-1] > 4.0  # ~0.41 km lost on every diagonal
    # a turn costs up to half a km, made up on the next legs: the lag never builds up
    assert timed.max() < 0.6 and timed[-1] < 0.15 and np.median(timed) < 0.1


def test_leg_speed_limits():
    model = PlaneModel()
    a, b = np.array([[10.5, 10.5]]), np.array([[11.5, 11.5]])
    on_time = leg_speed_mps(model, a, a, b, 141.4, STEP_S)[0]
    assert abs(on_time - 141.4) < 0.5  # already at sqrt(2) v on a diagonal: keep it
    from_cruise = leg_speed_mps(model, a, a, b, 100.0, STEP_S)[0]
    assert from_cruise == model.max_speed_mps  # 5 m/s^2 cannot make 1.41 km from 100 m/s
    past = leg_speed_mps(model, b + 0.2, a, b, 120.0, STEP_S)[0]
    assert past == model.min_speed_mps  # ahead of the grid clock: as slow as allowed
    assert leg_speed_mps(model, a, a, a, 140.0, STEP_S)[0] == model.speed_mps  # circle here
    orthogonal = leg_speed_mps(model, a, a, a + [1.0, 0.0], 100.0, STEP_S)[0]
    assert abs(orthogonal - 100.0) < 1e-6


def test_daemon_sends_leg_airspeeds_and_cruise_before_rtl(paper10, udp_port, fake_swarm_factory):
    swarm = fake_swarm_factory(2, udp_port)
    # twelve steps out in the area (home_by_end would keep half of them for the way home,
    # flown straight at cruise)
    searching = paper10.with_config(home_by_end=False)
    report = MissionDaemon(searching, options(udp_port, expect=2)).fly()
    assert report.result["refused_commands"] == 0
    # the fake vehicles start 2.9 km apart: closer than d_min and two 1.07 km circles at
    # cruise, so after RTL each gets its home circle's slower airspeed
    home_speeds = report.result["home_circle_speeds_mps"]
    for v in swarm.vehicles:
        *legs, home_speed = v.speeds
        assert home_speed == pytest.approx(home_speeds[str(v.sysid)], abs=0.05)
        assert 60 <= home_speed < 100 and v.mode == 11
        assert len(legs) >= 3 and all(100 <= s <= 150 for s in legs)
        assert max(legs) > 120  # diagonal legs and catching up
        assert legs[-1] == 100  # back to cruise, then RTL


def test_refused_airspeed_falls_back_to_cruise(paper10, udp_port, fake_swarm_factory):
    """An airframe that refuses the leg airspeeds (outside its AIRSPEED_MIN/MAX): one warning,
    the mission flies on at the scenario's speed, and the daemon stops asking."""
    swarm = fake_swarm_factory(2, udp_port, refuse_command=mavlink.MAV_CMD_DO_CHANGE_SPEED)
    said: list[str] = []
    report = MissionDaemon(paper10, options(udp_port, expect=2, progress=said.append)).fly()
    result = report.result
    assert result["steps"] == 12 and result["refused_commands"] >= 1
    warnings = [s for s in said if "MAV_CMD_DO_CHANGE_SPEED" in s]
    assert len(warnings) == 1 and "--airspeed-range" in warnings[0]
    for v in swarm.vehicles:
        asked = v.commands.count(mavlink.MAV_CMD_DO_CHANGE_SPEED)
        # the refused leg speed, the cruise reset and the home circle's speed, not once a step
        assert 1 <= asked <= 3
        assert v.speeds == [] and v.mode == 11


def test_cli_airspeed_range_errors_are_one_line(udp_port, tmp_path):
    from loopback import run_swarmplan

    for value, words in (
        ("100", "expected MIN:MAX in m/s"),
        ("150:120", "need 0 < MIN <= MAX"),
        ("120:150", "must hold the scenario's speed 100 m/s"),
    ):
        proc = run_swarmplan(
            ["daemon", "--connect", f"udpin:127.0.0.1:{udp_port}", "--airspeed-range", value,
             "--timeout", "1", "--out", str(tmp_path)],
            timeout=60,
        )  # fmt: skip
        assert proc.returncode == 2, value
        assert "Traceback" not in proc.stderr
        last = proc.stderr.strip().splitlines()[-1]
        assert words in last and "--airspeed-range" in last, last


def test_a_leg_too_fast_near_a_threat_is_flown_at_cruise_speed_not_replaced(paper10):
    """Near a threat the loiter circle at a leg-timed 150 m/s (2.4 km) can reach into the margin
    where the one at cruise speed (1.07 km) does not: the planner's cell is then kept and flown at
    cruise speed (late, but where the planner asked), and no override is counted."""
    from mavlink_bridge.safety.flight_envelope import FlightEnvelope
    from mavlink_bridge.safety.safety_envelope import SafetyEnvelope

    cells = SafetyEnvelope.for_scenario(paper10, 1.0, 1.0)
    envelope = FlightEnvelope(cells, PlaneModel())
    grid = cells.grid
    centre = cells.threat_xy_km[int(np.argmax(cells.threat_radius_km))]
    tried = kept = 0
    for offset in np.ndindex(19, 19):  # cells around the zone, flying east
        cell = grid.cell_of(centre + np.array(offset) - 9)
        for heading in (1, 7):  # a diagonal leg, 45 degrees left or right
            nxt = cell + HEADING_STEPS[heading]
            aim = cells.aim_point_km(cell, nxt, 1.0)
            fast = envelope._loiter_clearance(aim[None], np.array([150.0]))[0]
            slow = envelope._loiter_clearance(aim[None], np.array([100.0]))[0]
            if cells.static_reason(cell, nxt, 0.0, grid.centre_km(cell)) or not (
                fast < envelope.threat_margin_km <= slow
            ):
                continue
            tried += 1
            choice = envelope.choose(
                grid.centre_km(cell)[None], np.zeros(1), np.full(1, 100.0), cell[None],
                np.zeros(1, dtype=int), nxt[None], np.full(1, heading), np.full((1, 2), np.nan),
                np.zeros(1), grid.centre_km(cell)[None], np.ones(1, dtype=bool), 1.0,
            )  # fmt: skip
            assert choice.speeds_mps[0] < 150.0  # never the leg speed whose circle is unsafe
            if np.array_equal(choice.next_cells[0], nxt):
                kept += 1
                assert choice.speeds_mps[0] == 100.0 and sum(choice.overrides.values()) == 0
    assert tried >= 10 and kept >= 0.8 * tried, (tried, kept)
