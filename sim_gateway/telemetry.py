"""How each telemetry message of a simulated vehicle is built (:data:`BUILDERS`, by name), from
the vehicle and the frame's :class:`~sim_gateway.telemetry_streams.FleetSnapshot`. Which
messages are due and how often is ``sim_gateway/telemetry_streams.py``.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_gateway.auto_mission import mission_current
from sim_gateway.telemetry_streams import FleetSnapshot
from sim_gateway.vehicle import Vehicle


def _ground_speed_mps(v: Vehicle) -> float:
    """This vehicle's ground speed: its airspeed when flying (no wind), else 0."""
    return float(v.fleet.airspeed_mps[v.index]) if v.airborne else 0.0


def build_heartbeat(v: Vehicle, s: FleetSnapshot) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_FIXED_WING,
        mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
        v.base_mode(),
        v.mode,
        v.system_status(),
        3,
    )


SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink.MAV_SYS_STATUS_SENSOR_DIFFERENTIAL_PRESSURE
    | mavlink.MAV_SYS_STATUS_AHRS
    | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
)


def build_sys_status(v: Vehicle, s: FleetSnapshot) -> mavlink.MAVLink_message:
    present = enabled = health = SENSORS
    fence_on = bool(v.params["FENCE_ENABLE"]) and v.missions.count(1) > 0
    present |= mavlink.MAV_SYS_STATUS_GEOFENCE
    if fence_on:
        enabled |= mavlink.MAV_SYS_STATUS_GEOFENCE
    if not v.fence_breached:
        health |= mavlink.MAV_SYS_STATUS_GEOFENCE
    if v.booting:
        health &= ~(mavlink.MAV_SYS_STATUS_AHRS | mavlink.MAV_SYS_STATUS_SENSOR_GPS)
    if v.range_exhausted:
        health &= ~mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
    # the pre-arm verdict, as ArduPilot's GCS::update_sensor_status_flags gives it: present
    # always, enabled while arming checks are on (ARMING_CHECK), healthy when armed or when the
    # checks pass (MAVSDK's health.is_armable reads this bit)
    present |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
    if v.params["ARMING_CHECK"]:
        enabled |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
        if v.armed or v.prearm_failure() is None:
            health |= mavlink.MAV_SYS_STATUS_PREARM_CHECK
    pct = s.range_remaining_pct[v.index]
    return mavlink.MAVLink_sys_status_message(
        present,
        enabled,
        health,
        100,
        12600,
        1000 if v.armed else 0,
        pct,
        0,
        0,
        0,
        0,
        0,
        0,
    )


def build_global_position_int(v: Vehicle, s: FleetSnapshot) -> mavlink.MAVLink_message:
    i, f = v.index, v.fleet
    speed = _ground_speed_mps(v)
    course = float(f.course_rad[i])
    rel = float(f.alt_m[i])
    return mavlink.MAVLink_global_position_int_message(
        s.time_boot_ms,
        s.lat_e7[i],
        s.lon_e7[i],
        round((v.host.home_amsl_m() + rel) * 1000),
        round(rel * 1000),
        round(speed * math.cos(course) * 100),
        round(speed * math.sin(course) * 100),
        round(-float(f.climb_rate_mps[i]) * 100),
        round(math.degrees(course) * 100) % 36000,
    )


def build_attitude(v: Vehicle, s: FleetSnapshot) -> mavlink.MAVLink_message:
    i, f = v.index, v.fleet
    speed = max(float(f.airspeed_mps[i]), 1.0)
    pitch = math.atan2(float(f.climb_rate_mps[i]), speed) if v.airborne else 0.0
    yaw = math.atan2(math.sin(float(f.course_rad[i])), math.cos(float(f.course_rad[i])))
    yawspeed = 9.80665 * math.tan(float(f.bank_rad[i])) / speed if v.airborne else 0.0
    return mavlink.MAVLink_attitude_message(
        s.time_boot_ms, float(f.bank_rad[i]), pitch, yaw, 0.0, 0.0, yawspeed
    )


def build_vfr_hud(v: Vehicle, s: FleetSnapshot) -> mavlink.MAVLink_message:
    i, f = v.index, v.fleet
    speed = _ground_speed_mps(v)
    heading = round(math.degrees(float(f.course_rad[i]))) % 360
    return mavlink.MAVLink_vfr_hud_message(
        speed,
        speed,
        heading,
        60 if v.airborne else 0,
        v.host.home_amsl_m() + float(f.alt_m[i]),
        float(f.climb_rate_mps[i]),
    )


def build_gps_raw_int(v: Vehicle, s: FleetSnapshot) -> mavlink.MAVLink_message:
    i, f = v.index, v.fleet
    fix = (
        mavlink.GPS_FIX_TYPE_NO_FIX
        if v.host.sim_time_s < v.host.boot_s / 2
        else mavlink.GPS_FIX_TYPE_3D_FIX
    )
    alt_mm = round((v.host.home_amsl_m() + float(f.alt_m[i])) * 1000)
    return mavlink.MAVLink_gps_raw_int_message(
        s.time_boot_ms * 1000,
        fix,
        s.lat_e7[i],
        s.lon_e7[i],
        alt_mm,
        80,
        120,
        round(_ground_speed_mps(v) * 100),
        round(math.degrees(float(f.course_rad[i])) * 100) % 36000,
        14 if fix == mavlink.GPS_FIX_TYPE_3D_FIX else 0,
    )


def build_extended_sys_state(v: Vehicle, s: FleetSnapshot) -> mavlink.MAVLink_message:
    if not v.airborne:
        landed = mavlink.MAV_LANDED_STATE_ON_GROUND
    elif (
        v.fleet.climb_rate_mps[v.index] > 0.5
        and v.fleet.alt_m[v.index] < v.params["TKOFF_ALT"] * 0.5
    ):
        landed = mavlink.MAV_LANDED_STATE_TAKEOFF
    else:
        landed = mavlink.MAV_LANDED_STATE_IN_AIR
    return mavlink.MAVLink_extended_sys_state_message(mavlink.MAV_VTOL_STATE_UNDEFINED, landed)


def build_home_position(v: Vehicle, s: FleetSnapshot) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_home_position_message(
        s.home_lat_e7[v.index],
        s.home_lon_e7[v.index],
        round(v.host.home_amsl_m() * 1000),
        0.0,
        0.0,
        0.0,
        [1.0, 0.0, 0.0, 0.0],
        0.0,
        0.0,
        0.0,
        time_usec=s.time_boot_ms * 1000,
    )


def build_mission_current(v: Vehicle, s: FleetSnapshot) -> mavlink.MAVLink_message:
    return mission_current(v.missions, v.mode)


def build_system_time(v: Vehicle, s: FleetSnapshot) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_system_time_message(s.time_unix_us, s.time_boot_ms)


BUILDERS = {
    "HEARTBEAT": build_heartbeat,
    "SYS_STATUS": build_sys_status,
    "GLOBAL_POSITION_INT": build_global_position_int,
    "ATTITUDE": build_attitude,
    "VFR_HUD": build_vfr_hud,
    "GPS_RAW_INT": build_gps_raw_int,
    "EXTENDED_SYS_STATE": build_extended_sys_state,
    "HOME_POSITION": build_home_position,
    "MISSION_CURRENT": build_mission_current,
    "SYSTEM_TIME": build_system_time,
}


def build_autopilot_version(v: Vehicle) -> mavlink.MAVLink_message:
    """AUTOPILOT_VERSION of an ArduPlane 4.5.7 (official) without MAVLink FTP."""
    caps = (
        mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
        | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
        | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
        | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
        | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
        | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
        | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
        | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
    )
    version = (4 << 24) | (5 << 16) | (7 << 8) | mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL
    return mavlink.MAVLink_autopilot_version_message(
        caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, v.sysid, uid2=[0] * 18
    )
