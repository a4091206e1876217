"""The simulated vehicles over real loopback UDP, driven by a pymavlink ground station."""

from __future__ import annotations

import math

import numpy as np
from pymavlink import mavutil
from sim_harness import take_off

from mavlink_wire.looks import parse_look_url
from planner.geodesy import geodetic_to_local_km
from planner.grid import Grid

ml = mavutil.mavlink


def test_heartbeat_identity_and_telemetry_of_every_vehicle(gcs, sim_factory):
    sim_factory(scenario="paper-10uav")
    wanted = {
        "HEARTBEAT",
        "SYS_STATUS",
        "GLOBAL_POSITION_INT",
        "ATTITUDE",
        "VFR_HUD",
        "GPS_RAW_INT",
        "HOME_POSITION",
        "EXTENDED_SYS_STATE",
    }
    seen: dict[int, set[str]] = {}
    for _ in range(4000):
        m = gcs.wait(list(wanted), timeout=3)
        assert m is not None
        seen.setdefault(m.get_srcSystem(), set()).add(m.get_type())
        if m.get_type() == "HEARTBEAT":
            assert m.get_srcComponent() == 1
            assert (
                m.type == ml.MAV_TYPE_FIXED_WING and m.autopilot == ml.MAV_AUTOPILOT_ARDUPILOTMEGA
            )
            assert m.base_mode & ml.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            assert m.custom_mode == 0
        if len(seen) == 10 and all(s == wanted for s in seen.values()):
            break
    assert sorted(seen) == list(range(1, 11))
    assert all(s == wanted for s in seen.values())


def test_boot_phase_refuses_arming_and_missions_then_standby(gcs, sim_factory):
    sim_factory(boot_s=20.0, speedup=10.0)
    hb = gcs.wait("HEARTBEAT", 1)
    assert hb.system_status in (ml.MAV_STATE_BOOT, ml.MAV_STATE_CALIBRATING)
    ack = gcs.command_long(1, ml.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert ack.result == ml.MAV_RESULT_FAILED
    gcs.mav.mission_count_send(1, 1, 2, 0)
    assert gcs.wait("MISSION_ACK", 1).type == ml.MAV_MISSION_NO_SPACE
    assert gcs.wait(
        "HEARTBEAT", 1, timeout=5, cond=lambda m: m.system_status == ml.MAV_STATE_STANDBY
    )
    assert gcs.command_long(1, ml.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == ml.MAV_RESULT_ACCEPTED
    hb = gcs.wait("HEARTBEAT", 1, cond=lambda m: m.base_mode & ml.MAV_MODE_FLAG_SAFETY_ARMED)
    assert hb is not None


def test_prearm_statustext_during_boot(gcs, sim_factory):
    sim_factory(boot_s=20.0, speedup=1.0)
    gcs.ensure_peer()
    gcs.mav.command_long_send(1, 1, ml.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    text = gcs.wait("STATUSTEXT", 1, cond=lambda m: m.text.startswith("PreArm"))
    assert text is not None


def test_takeoff_then_reposition_as_command_int_only(gcs, sim_factory):
    running = sim_factory(speedup=20.0)
    take_off(gcs)
    sim = running.sim
    lat, lon = sim.local_to_geodetic(20_000.0, 10_000.0)
    long_ack = gcs.command_long(1, ml.MAV_CMD_DO_REPOSITION, -1, 1, 0, 0, lat, lon, 300)
    assert long_ack.result == ml.MAV_RESULT_UNSUPPORTED
    ack = gcs.command_int(
        1,
        ml.MAV_CMD_DO_REPOSITION,
        ml.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        -1,
        1,
        0,
        0,
        round(lat * 1e7),
        round(lon * 1e7),
        300,
    )
    assert ack.result == ml.MAV_RESULT_ACCEPTED
    hb = gcs.wait("HEARTBEAT", 1, cond=lambda m: m.custom_mode == 15)
    assert hb is not None
    # heading for the target: the distance to it shrinks
    d0 = math.hypot(sim.fleet.x_m[0] - 20_000, sim.fleet.y_m[0] - 10_000)
    gcs.wait("GLOBAL_POSITION_INT", 1, timeout=3)
    gcs.wait("HEARTBEAT", 1)
    d1 = math.hypot(sim.fleet.x_m[0] - 20_000, sim.fleet.y_m[0] - 10_000)
    assert d1 < d0


def test_bad_command_values_are_refused_and_counted(gcs, sim_factory):
    running = sim_factory()
    gcs.heartbeat()
    assert gcs.command_long(1, ml.MAV_CMD_DO_SET_MODE, 1, 99).result == ml.MAV_RESULT_FAILED
    assert (
        gcs.command_long(1, ml.MAV_CMD_DO_SET_MODE, 1, float("nan")).result == ml.MAV_RESULT_DENIED
    )
    assert gcs.command_long(1, ml.MAV_CMD_COMPONENT_ARM_DISARM, 7).result == ml.MAV_RESULT_DENIED
    assert gcs.command_long(1, ml.MAV_CMD_REQUEST_MESSAGE, -3).result == ml.MAV_RESULT_DENIED
    assert gcs.command_long(1, 31999).result == ml.MAV_RESULT_UNSUPPORTED
    ack = gcs.command_int(
        1, ml.MAV_CMD_DO_REPOSITION, ml.MAV_FRAME_GLOBAL_INT, -1, 1, 0, 0, 10**9, 10**9, 100
    )
    assert ack.result == ml.MAV_RESULT_DENIED
    assert running.sim.stats.rejected_commands >= 6
    assert gcs.command_long(1, ml.MAV_CMD_DO_SET_MODE, 1, 12).result == ml.MAV_RESULT_ACCEPTED


def test_request_message_autopilot_version_and_home(gcs, sim_factory):
    sim_factory()
    assert gcs.command_long(2, ml.MAV_CMD_REQUEST_MESSAGE, 148).result == ml.MAV_RESULT_ACCEPTED
    version = gcs.wait("AUTOPILOT_VERSION", 2)
    caps = version.capabilities
    for flag in (
        ml.MAV_PROTOCOL_CAPABILITY_MISSION_INT,
        ml.MAV_PROTOCOL_CAPABILITY_COMMAND_INT,
        ml.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE,
        ml.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT,
    ):
        assert caps & flag
    assert not caps & ml.MAV_PROTOCOL_CAPABILITY_FTP
    assert gcs.command_long(2, ml.MAV_CMD_REQUEST_MESSAGE, 242).result == ml.MAV_RESULT_ACCEPTED
    assert gcs.wait("HOME_POSITION", 2) is not None
    ack = gcs.command_long(2, ml.MAV_CMD_SET_MESSAGE_INTERVAL, 33, 50_000)
    assert ack.result == ml.MAV_RESULT_ACCEPTED


def test_parameter_protocol(gcs, sim_factory):
    sim_factory()
    gcs.mav.param_request_list_send(1, 1)
    values = {}
    while True:
        m = gcs.wait("PARAM_VALUE", 1, timeout=3)
        assert m is not None
        values[m.param_id] = m
        if len(values) == m.param_count:
            break
    assert values["SYSID_THISMAV"].param_value == 1
    assert values["AIRSPEED_CRUISE"].param_value == 100
    gcs.mav.param_set_send(1, 1, b"WP_LOITER_RAD", 250, ml.MAV_PARAM_TYPE_INT16)
    assert (
        gcs.wait("PARAM_VALUE", 1, cond=lambda m: m.param_id == "WP_LOITER_RAD").param_value == 250
    )
    gcs.mav.param_set_send(1, 1, b"ROLL_LIMIT_DEG", 500, ml.MAV_PARAM_TYPE_REAL32)  # out of range
    assert (
        gcs.wait("PARAM_VALUE", 1, cond=lambda m: m.param_id == "ROLL_LIMIT_DEG").param_value == 45
    )
    gcs.mav.param_request_read_send(1, 1, b"FS_GCS_ENABL", -1)
    assert gcs.wait("PARAM_VALUE", 1, cond=lambda m: m.param_id == "FS_GCS_ENABL").param_value == 0


def _upload(gcs, sysid, items, mission_type=0):
    gcs.mav.mission_count_send(sysid, 1, len(items), mission_type)
    while True:
        m = gcs.wait(["MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"], sysid)
        assert m is not None
        if m.get_type() == "MISSION_ACK":
            return m
        it = items[m.seq]
        gcs.mav.mission_item_int_send(
            sysid, 1, m.seq, it[0], it[1], 0, 1, *it[2:6], it[6], it[7], it[8], mission_type
        )


def test_mission_upload_download_and_auto_flight(gcs, sim_factory):
    running = sim_factory(speedup=50.0)
    sim = running.sim
    wp = [sim.local_to_geodetic(12_000.0, 14_000.0), sim.local_to_geodetic(16_000.0, 12_000.0)]
    e7 = [(round(a * 1e7), round(b * 1e7)) for a, b in wp]
    items = [
        (0, 16, 0, 0, 0, 0, *e7[0], 584.0),
        (3, 22, 0, 0, 0, 0, 0, 0, 150.0),
        (3, 16, 0, 0, 0, 0, *e7[0], 200.0),
        (3, 16, 0, 0, 0, 0, *e7[1], 200.0),
    ]
    assert _upload(gcs, 1, items).type == ml.MAV_MISSION_ACCEPTED
    gcs.mav.mission_request_list_send(1, 1, 0)
    assert gcs.wait("MISSION_COUNT", 1).count == 4
    gcs.mav.mission_request_int_send(1, 1, 2, 0)
    item = gcs.wait("MISSION_ITEM_INT", 1)
    assert (item.seq, item.command, item.x, item.y) == (2, 16, *e7[0])
    gcs.mav.mission_ack_send(1, 1, 0, 0)
    gcs.heartbeat()
    assert gcs.command_long(1, ml.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
    assert gcs.command_long(1, ml.MAV_CMD_DO_SET_MODE, 1, 10).result == 0
    reached = set()
    for _ in range(200):
        gcs.heartbeat()
        m = gcs.wait("MISSION_ITEM_REACHED", 1, timeout=0.5)
        if m is not None:
            reached.add(m.seq)
        if {1, 2, 3} <= reached:
            break
    assert {1, 2, 3} <= reached
    # mission complete -> RTL, as ArduPlane
    assert gcs.wait("HEARTBEAT", 1, cond=lambda m: m.custom_mode == 11) is not None


def test_fence_exclusion_refuses_targets_and_breach_triggers_rtl(gcs, sim_factory):
    running = sim_factory(speedup=5.0)
    sim = running.sim
    take_off(gcs)
    x0, y0 = float(sim.fleet.x_m[0]), float(sim.fleet.y_m[0])
    centre = sim.local_to_geodetic(x0 + 6000.0, y0)
    fence = [(5, 5004, 2000.0, 0, 0, 0, round(centre[0] * 1e7), round(centre[1] * 1e7), 0.0)]
    assert _upload(gcs, 1, fence, mission_type=1).type == ml.MAV_MISSION_ACCEPTED
    ack = gcs.command_int(
        1,
        ml.MAV_CMD_DO_REPOSITION,
        ml.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        -1,
        1,
        0,
        0,
        round(centre[0] * 1e7),
        round(centre[1] * 1e7),
        300,
    )
    assert ack.result == ml.MAV_RESULT_DENIED
    # fly through it: put the vehicle at its edge heading in (a gust would do), and watch
    sim.fleet.x_m[0], sim.fleet.y_m[0] = x0 + 3900.0, y0
    sim.fleet.course_rad[0] = math.pi / 2
    status = gcs.wait(
        "SYS_STATUS",
        1,
        timeout=5,
        cond=lambda m: not m.onboard_control_sensors_health & ml.MAV_SYS_STATUS_GEOFENCE,
    )
    assert status is not None
    assert status.onboard_control_sensors_enabled & ml.MAV_SYS_STATUS_GEOFENCE
    assert gcs.wait("HEARTBEAT", 1, cond=lambda m: m.custom_mode == 11) is not None


def test_gcs_failsafe_acts_as_arduplane(gcs, sim_factory):
    """ArduPlane's GCS failsafe: one stage after FS_LONG_TIMEOUT; in GUIDED, FS_LONG_ACTN 0 carries
    on (the plane circles its guided target) and 1 returns home."""
    running = sim_factory(speedup=20.0)
    take_off(gcs)
    for name, value in (("FS_GCS_ENABL", 1), ("FS_LONG_TIMEOUT", 1.0), ("FS_LONG_ACTN", 0)):
        gcs.mav.param_set_send(1, 1, name.encode(), value, ml.MAV_PARAM_TYPE_REAL32)
        assert (
            gcs.wait("PARAM_VALUE", 1, cond=lambda m, n=name: m.param_id == n).param_value == value
        )
    assert gcs.command_long(1, ml.MAV_CMD_DO_SET_MODE, 1, 15).result == 0
    vehicle = running.sim.vehicles[0]
    # silence: no more heartbeats from the ground station
    text = gcs.wait("STATUSTEXT", 1, timeout=5, cond=lambda m: "GCS Failsafe On" in m.text)
    assert text is not None and "GUIDED" in text.text
    assert vehicle.failsafe.stage == 2 and vehicle.mode == 15  # carried on in GUIDED
    gcs.heartbeat()
    assert gcs.wait("STATUSTEXT", 1, timeout=5, cond=lambda m: "Cleared" in m.text) is not None
    gcs.mav.param_set_send(1, 1, b"FS_LONG_ACTN", 1, ml.MAV_PARAM_TYPE_REAL32)
    assert gcs.wait("HEARTBEAT", 1, timeout=5, cond=lambda m: m.custom_mode == 11) is not None
    assert vehicle.failsafe.stage == 2


def test_sensor_looks_follow_the_documented_mapping(gcs, sim_factory):
    running = sim_factory(speedup=50.0, airborne=True)
    sim = running.sim
    cfg = sim.config
    grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
    footprint = {tuple(o) for o in grid.disc_offsets(cfg.detection_radius_km)}
    indices: dict[int, list[int]] = {1: [], 2: []}
    for _ in range(400):
        m = gcs.wait("CAMERA_IMAGE_CAPTURED", timeout=5)
        assert m is not None and m.get_srcComponent() == 100
        assert m.capture_result == 1 and m.camera_id == 0 and list(m.q) == [1, 0, 0, 0]
        assert m.file_url.startswith("look:") or m.file_url.startswith("look+:")
        assert set(parse_look_url(m.file_url)) <= footprint
        x, y = geodetic_to_local_km(m.lat / 1e7, m.lon / 1e7, sim.origin)
        assert 0 <= x[0] < 100 and 0 <= y[0] < 100
        if m.file_url.startswith("look:"):
            indices[m.get_srcSystem()].append(m.image_index)
        if min(len(v) for v in indices.values()) >= 4:
            break
    for seq in indices.values():
        assert seq[:4] == list(range(seq[0], seq[0] + 4))
    assert abs(m.relative_alt - 500_000) < 5000


def test_engagement_is_resolved_once_per_sequence_number(gcs, sim_factory):
    running = sim_factory(speedup=5.0, airborne=True)
    sim = running.sim
    target = int(np.flatnonzero(sim.world.alive)[0])
    tx, ty = sim.world.positions[target] * 1000.0
    sim.fleet.x_m[1], sim.fleet.y_m[1] = tx + 100.0, ty
    sim.fleet.set_airspeed(1, 1.0, at_once=True)  # stay put while the request is in flight
    ack = gcs.command_long(2, ml.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 1, 7, comp=100)
    assert ack.get_srcComponent() == 100 and ack.result == ml.MAV_RESULT_ACCEPTED
    assert ack.result_param2 == int(sim.world.target_ids[target])
    again = gcs.command_long(2, ml.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 1, 7, comp=100)
    assert again.result_param2 == ack.result_param2
    assert sim.engagements == 1
    miss = gcs.command_long(2, ml.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 1, 8, comp=100)
    assert miss.result == ml.MAV_RESULT_ACCEPTED and miss.result_param2 == 0
    assert gcs.wait("STATUSTEXT", 2, compid=100) is not None


def test_change_speed_is_bounded_by_airspeed_limits_and_ramps(gcs, sim_factory):
    """MAV_CMD_DO_CHANGE_SPEED as ArduPlane takes it: DENIED outside [AIRSPEED_MIN, AIRSPEED_MAX]
    (60..150 m/s for a 100 m/s plane); accepted speeds are reached at a bounded acceleration,
    seen in the ground speed of GLOBAL_POSITION_INT; -2 returns to AIRSPEED_CRUISE."""
    sim_factory(speedup=10.0, airborne=True)
    gcs.heartbeat()
    change = ml.MAV_CMD_DO_CHANGE_SPEED
    assert gcs.command_long(1, change, 0, 151, -1).result == ml.MAV_RESULT_DENIED
    assert gcs.command_long(1, change, 0, 59, -1).result == ml.MAV_RESULT_DENIED
    assert gcs.command_long(1, change, 0, 140, -1).result == ml.MAV_RESULT_ACCEPTED
    samples = []  # (simulated s, ground speed m/s)
    while not samples or samples[-1][1] < 139.5:
        m = gcs.wait("GLOBAL_POSITION_INT", 1, timeout=3)
        assert m is not None and len(samples) < 400
        samples.append((m.time_boot_ms / 1e3, math.hypot(m.vx, m.vy) / 100))
    t, v = np.array(samples).T
    assert v[0] < 110  # not at once: 40 m/s more takes ~8 s
    rates = np.diff(v) / np.maximum(np.diff(t), 1e-3)
    assert rates.max() < 5.0 * 1.1 and t[-1] - t[0] > 6.0
    assert gcs.command_long(1, change, 0, -2, -1).result == ml.MAV_RESULT_ACCEPTED
    assert gcs.wait(
        "GLOBAL_POSITION_INT", 1, timeout=5, cond=lambda m: abs(math.hypot(m.vx, m.vy) - 1e4) < 50
    )
