"""Whole missions against the real ArduPlane SITL binary (``ARDUPLANE_SITL``), with real
processes only: N SITL instances, ``swarmplan payload`` on their SERIAL1 ports (the world and each
plane's camera) and ``swarmplan daemon`` on their SERIAL0 ports (tests/sitl/sitl_mission.py).

* Three planes at 10x search, look, and engage at least one target, with no threat, separation
  or range violation: the whole issue-11 mission against a real autopilot (~3 min wall: the
  slowest SITL test).
* Two planes at real time (1x) become ready (pre-arm checks, GPS, home), arm, take off and fly
  two decision steps: ArduPlane needs ~20 s of its clock before it can arm (~1.5 min wall).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from pymavlink import mavutil
from sitl_mission import fly_sitl_mission, turn_breaks_by_step_length


@pytest.mark.timeout(420)
def test_three_planes_with_the_payload_simulator_search_look_and_engage(sitl_binary, tmp_path):
    steps = 16
    run = fly_sitl_mission(
        sitl_binary, tmp_path, planes=3, speedup=10, scenario="arduplane-3uav", steps=steps,
        timeout_s=360,
    )  # fmt: skip
    assert run.returncode == 0, run.explain()
    result, payload = run.result, run.payload
    assert result is not None and payload is not None, run.explain()
    assert result["steps"] == steps
    # every plane's camera was heard: looks from the payload simulator reached the planner
    assert result["uavs_without_camera"] == [], run.explain()
    assert all(n >= steps - 2 for n in payload["looks_per_vehicle"]), payload
    assert result["coverage"] > 0.2
    # at least one target engaged, the same ones in the daemon's account and in ground truth
    engaged = sorted(e["target_id"] for e in result["engagements"])
    assert engaged, run.explain()
    assert engaged == payload["targets_engaged"], (engaged, payload)
    # safety at the decision steps and along every position report, the flight home included.
    # The turn rule is the planner's grid rule judged on the flown positions at the decision
    # steps: a plane held circling breaks it. Holds came from the envelope's predicted
    # separation around targets never circled and from replacements into dead ends (0-6 breaks
    # in 16 steps); with both fixed 0 in 3 runs, and one run with the first fix alone had 1:
    # two planes' legs crossing at one instant, one had to circle (docs/sitl.md). Counted on the
    # regular steps the plan did not ask for: a machine that stalls the daemon or the autopilots
    # (a step of the planes' clock longer or shorter than the period by 10 %) leaves planes
    # circling their targets meanwhile, and a circle the plan asked for (a suspect, a target
    # before it is engaged) is the plan's (CI had 4 and 5 in one run each, on a loaded machine)
    v = result["violations"]
    assert (v["threat"], v["separation"], v["range"]) == (0, 0, 0), run.explain()
    breaks = turn_breaks_by_step_length(result, run.step_s)
    facts = {
        **breaks,
        **{k: result.get(k) for k in ("late_steps", "max_lateness_s", "held_steps", "lost_uavs")},
        "overrides": result["envelope_overrides"],
        "engaged": engaged,
    }
    assert breaks["turn_breaks_regular_steps"] <= 1, (facts, run.explain())
    for phase, audit in result["track_audit"]["phases"].items():
        assert audit["threat_entries"] == 0 and audit["separation_breaches"] == 0, (phase, audit)
    # every plane sent home: RTL, or guided around the threats where the straight line crosses
    home = set(result["rtl_sent_to"]) | set(result["guided_home_around_threats"])
    assert sorted(home) == [1, 2, 3], result["rtl_not_sent"]


@pytest.mark.xdist_group("realtime")  # waits on the wall clock (tests/xdist_lanes.py)
@pytest.mark.timeout(300)
def test_two_planes_at_real_time_become_ready_arm_take_off_and_fly_two_steps(sitl_binary, tmp_path):
    """The 1x readiness check; the flight home is watched for 3 s only (at 1x it took 49 s of
    the test's 122, and the 3-plane test watches it to the end)."""
    scenario = Path(__file__).with_name("arduplane-1x.toml")
    run = fly_sitl_mission(
        sitl_binary, tmp_path, planes=2, speedup=1, scenario=str(scenario), steps=2,
        timeout_s=240, with_payload=False, daemon_args=["--rtl-watch", "3"],
    )  # fmt: skip
    assert run.returncode == 0, run.explain()
    text = run.daemon.text()
    # ready means ready: armed only once ArduPlane's own pre-arm checks pass (~20 s after boot)
    assert "armed 2 vehicles after" in text, run.explain()
    assert "airborne, GUIDED" in text
    result = run.result
    assert result is not None and result["steps"] == 2
    assert all(len(u["track_km"]) == 3 for u in result["uavs"])
    # safety (the turn limit is the planner's, judged at the decision steps: a plane that has
    # just climbed out and circles its first guided target does not fly the grid's first leg)
    v = result["violations"]
    assert (v["threat"], v["separation"], v["range"]) == (0, 0, 0), run.explain()
    # ArduPlane's own limits were read at launch (AIRSPEED_*, ROLL_LIMIT_DEG, WP_LOITER_RAD)
    assert "airframe vehicle 2: airspeed 10..30 m/s (cruise 22), bank limit 65 deg" in text
    assert "loiter radius 80 m" in text
    # no arm command before the vehicle's own pre-arm checks passed (its SYS_STATUS health bit)
    for sysid in (1, 2):
        healthy_s, arms_s = prearm_and_arms(run.out / "mission.tlog", sysid)
        assert healthy_s is not None and arms_s and arms_s[0] >= healthy_s, (sysid, arms_s)


def prearm_and_arms(tlog: Path, sysid: int) -> tuple[float | None, list[float]]:
    """From the daemon's tlog: when vehicle ``sysid`` first reported its pre-arm checks passing
    (SYS_STATUS health bit MAV_SYS_STATUS_PREARM_CHECK), and when each arm command went to it."""
    bit = mavutil.mavlink.MAV_SYS_STATUS_PREARM_CHECK
    log = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    healthy, arms = None, []
    while (msg := log.recv_match()) is not None:
        kind, when = msg.get_type(), getattr(msg, "_timestamp", 0.0)
        if kind == "SYS_STATUS" and msg.get_srcSystem() == sysid and healthy is None:
            if msg.onboard_control_sensors_health & bit:
                healthy = when
        elif (
            kind == "COMMAND_LONG"
            and msg.command == mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM
            and msg.target_system == sysid
            and msg.param1 == 1
        ):
            arms.append(when)
    return healthy, arms
