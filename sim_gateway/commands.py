"""MAV_CMD handlers of a simulated ArduPlane: one small function per command, each returning the
MAV_RESULT of its COMMAND_ACK. COMMAND_LONG and COMMAND_INT arrive here as one
:class:`CommandArgs`; like ArduPlane, MAV_CMD_DO_REPOSITION is only accepted as COMMAND_INT
(as COMMAND_LONG it is UNSUPPORTED). Commands for the camera component (100) are in
:data:`CAMERA_COMMANDS`. Nothing here releases a weapon or payload: such commands are UNSUPPORTED.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_gateway import flight_modes as modes
from sim_gateway.camera import engagement_sequence, engagement_text
from sim_gateway.geofence import point_excluded
from sim_gateway.mission_store import RELATIVE_FRAMES
from sim_gateway.telemetry import BUILDERS, build_autopilot_version
from sim_gateway.telemetry_streams import MESSAGE_IDS, NAMES_BY_ID
from sim_gateway.vehicle import GuidedTarget, Vehicle

FORCE_DISARM_MAGIC = 21196
#: a DO_SET_HOME farther than this from the vehicle is refused (ArduPilot: 50 km from EKF origin)
MAX_HOME_DISTANCE_M = 50_000.0
AMSL_FRAMES = (mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT)


@dataclass(frozen=True)
class CommandArgs:
    """A COMMAND_LONG or COMMAND_INT, normalised. For COMMAND_INT, ``x``/``y`` are degE7."""

    command: int
    params: tuple[float, float, float, float, float, float, float]
    peer: tuple[int, int]  # (sysid, compid) of the sender, for the ACK
    as_int: bool
    frame: int = 0
    x: int = 0
    y: int = 0

    @property
    def p1(self) -> float:
        return self.params[0]

    @property
    def p2(self) -> float:
        return self.params[1]

    @property
    def p3(self) -> float:
        return self.params[2]

    @property
    def p4(self) -> float:
        return self.params[3]


Result = int
CommandHandler = Callable[[Vehicle, CommandArgs], Result]


def _refuse(v: Vehicle, text: str | None) -> None:
    if text:
        v.statustext(text, mavlink.MAV_SEVERITY_WARNING)


def command_component_arm_disarm(v: Vehicle, c: CommandArgs) -> Result:
    if c.p1 == 1.0:
        result, reason = v.arm()
    elif c.p1 == 0.0:
        result, reason = v.disarm(force=c.p2 == FORCE_DISARM_MAGIC)
    else:
        v.host.stats.rejected_commands += 1
        return mavlink.MAV_RESULT_DENIED
    _refuse(v, reason)
    return result


def command_do_set_mode(v: Vehicle, c: CommandArgs) -> Result:
    if not math.isfinite(c.p2) or not int(c.p1) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        v.host.stats.rejected_commands += 1
        return mavlink.MAV_RESULT_DENIED
    mode = int(c.p2)
    if mode != c.p2 or not v.set_mode(mode):
        v.host.stats.rejected_commands += 1
        return mavlink.MAV_RESULT_FAILED
    return mavlink.MAV_RESULT_ACCEPTED


def command_do_reposition(v: Vehicle, c: CommandArgs) -> Result:
    """Guided target: COMMAND_INT only; lat/lon degE7 in x/y, z altitude in the frame's datum."""
    if not c.as_int:
        return mavlink.MAV_RESULT_UNSUPPORTED
    stats = v.host.stats
    if c.frame not in RELATIVE_FRAMES + AMSL_FRAMES:
        stats.rejected_commands += 1
        return mavlink.MAV_RESULT_FAILED
    if not (-90e7 <= c.x <= 90e7 and -180e7 <= c.y <= 180e7) or (c.x == 0 and c.y == 0):
        stats.rejected_commands += 1
        return mavlink.MAV_RESULT_DENIED
    change_mode = math.isfinite(c.p2) and int(c.p2) & mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE
    if v.mode != modes.GUIDED and not change_mode:
        return mavlink.MAV_RESULT_FAILED
    x_m, y_m = v.host.geodetic_to_local(c.x / 1e7, c.y / 1e7)
    if v.params["FENCE_ENABLE"] and point_excluded(v.host.fence_circles(v.index), x_m, y_m):
        v.statustext("Guided target inside fence exclusion", mavlink.MAV_SEVERITY_WARNING)
        stats.rejected_commands += 1
        return mavlink.MAV_RESULT_DENIED
    z = c.params[6]
    if not math.isfinite(z):
        alt = float(v.fleet.target_alt_m[v.index])
    else:
        alt = z if c.frame in RELATIVE_FRAMES else z - v.host.home_amsl_m()
    radius = c.p3 if math.isfinite(c.p3) and c.p3 != 0 else v.params["WP_LOITER_RAD"]
    v.set_guided_target(GuidedTarget(x_m, y_m, alt, radius))
    if v.mode != modes.GUIDED:
        v.set_mode(modes.GUIDED)
    return mavlink.MAV_RESULT_ACCEPTED


def command_nav_return_to_launch(v: Vehicle, c: CommandArgs) -> Result:
    v.set_mode(modes.RTL)
    return mavlink.MAV_RESULT_ACCEPTED


def command_mission_start(v: Vehicle, c: CommandArgs) -> Result:
    if len(v.missions.mission()) < 2:
        return mavlink.MAV_RESULT_FAILED
    first = int(c.p1) if math.isfinite(c.p1) and c.p1 >= 1 else 1
    v.missions.current_seq = min(first, len(v.missions.mission()) - 1)
    return mavlink.MAV_RESULT_ACCEPTED if v.set_mode(modes.AUTO) else mavlink.MAV_RESULT_FAILED


def command_do_set_mission_current(v: Vehicle, c: CommandArgs) -> Result:
    seq = int(c.p1) if math.isfinite(c.p1) else -1
    if not v.set_current_item(seq):
        v.host.stats.rejected_commands += 1
        return mavlink.MAV_RESULT_DENIED
    return mavlink.MAV_RESULT_ACCEPTED


def command_do_change_speed(v: Vehicle, c: CommandArgs) -> Result:
    """param1 speed type (0 airspeed, 1 ground speed: the same without wind), param2 m/s: -1 no
    change, -2 back to AIRSPEED_CRUISE; outside [AIRSPEED_MIN, AIRSPEED_MAX] DENIED (as
    ArduPlane). The plane reaches the new speed at its acceleration limit."""
    speed = v.params["AIRSPEED_CRUISE"] if c.p2 == -2 else c.p2
    if c.p2 == -1 and c.p1 in (0, 1):
        return mavlink.MAV_RESULT_ACCEPTED
    if (
        c.p1 not in (0, 1)
        or not math.isfinite(speed)
        or not v.params["AIRSPEED_MIN"] <= speed <= v.params["AIRSPEED_MAX"]
    ):
        v.host.stats.rejected_commands += 1
        return mavlink.MAV_RESULT_DENIED
    v.fleet.set_airspeed(v.index, speed)
    return mavlink.MAV_RESULT_ACCEPTED


def command_request_message(v: Vehicle, c: CommandArgs) -> Result:
    if not math.isfinite(c.p1) or c.p1 < 0 or c.p1 != int(c.p1):
        v.host.stats.rejected_commands += 1
        return mavlink.MAV_RESULT_DENIED
    msg_id = int(c.p1)
    if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
        return command_request_autopilot_capabilities(v, c)
    name = NAMES_BY_ID.get(msg_id)
    if name is None:
        return mavlink.MAV_RESULT_UNSUPPORTED
    if name == "HOME_POSITION" and v.booting:
        return mavlink.MAV_RESULT_FAILED  # no home before the GPS / EKF is ready
    v.ack(c.command, mavlink.MAV_RESULT_ACCEPTED, c.peer)
    v.send(BUILDERS[name](v, v.host.snapshot()))
    return -1


def command_request_autopilot_capabilities(v: Vehicle, c: CommandArgs) -> Result:
    v.ack(c.command, mavlink.MAV_RESULT_ACCEPTED, c.peer)
    v.send(build_autopilot_version(v))
    return -1


def command_set_message_interval(v: Vehicle, c: CommandArgs) -> Result:
    if not (math.isfinite(c.p1) and math.isfinite(c.p2)):
        v.host.stats.rejected_commands += 1
        return mavlink.MAV_RESULT_DENIED
    name = NAMES_BY_ID.get(int(c.p1))
    if name is None:
        return mavlink.MAV_RESULT_UNSUPPORTED
    if name == "HEARTBEAT":
        return mavlink.MAV_RESULT_DENIED
    interval_us = c.p2
    if interval_us == 0:
        v.streams.reset_default(name)
    elif interval_us < 0:
        v.streams.set_rate_hz(name, None)
    else:
        v.streams.set_rate_hz(name, 1e6 / interval_us)
    return mavlink.MAV_RESULT_ACCEPTED


def command_get_message_interval(v: Vehicle, c: CommandArgs) -> Result:
    name = NAMES_BY_ID.get(int(c.p1)) if math.isfinite(c.p1) else None
    if name is None:
        return mavlink.MAV_RESULT_UNSUPPORTED
    interval = v.streams.interval_s.get(name)
    v.ack(c.command, mavlink.MAV_RESULT_ACCEPTED, c.peer)
    v.send(
        mavlink.MAVLink_message_interval_message(
            MESSAGE_IDS[name], -1 if interval is None else round(interval * 1e6)
        )
    )
    return -1


def command_do_set_home(v: Vehicle, c: CommandArgs) -> Result:
    if c.p1 == 1:
        v.home_x_m, v.home_y_m = float(v.fleet.x_m[v.index]), float(v.fleet.y_m[v.index])
        return mavlink.MAV_RESULT_ACCEPTED
    lat, lon = (c.x / 1e7, c.y / 1e7) if c.as_int else (c.params[4], c.params[5])
    if not (math.isfinite(lat) and math.isfinite(lon) and -90 <= lat <= 90 and -180 <= lon <= 180):
        v.host.stats.rejected_commands += 1
        return mavlink.MAV_RESULT_DENIED
    x_m, y_m = v.host.geodetic_to_local(lat, lon)
    here_x, here_y = float(v.fleet.x_m[v.index]), float(v.fleet.y_m[v.index])
    if math.hypot(x_m - here_x, y_m - here_y) > MAX_HOME_DISTANCE_M:
        # as ArduPilot ("far from EKF origin"): a home this far is a corrupt or hostile command,
        # and its coordinates would not even fit HOME_POSITION's int32 fields
        v.host.stats.rejected_commands += 1
        return mavlink.MAV_RESULT_DENIED
    v.home_x_m, v.home_y_m = x_m, y_m
    return mavlink.MAV_RESULT_ACCEPTED


COMMANDS: dict[int, CommandHandler] = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: command_component_arm_disarm,
    mavlink.MAV_CMD_DO_SET_MODE: command_do_set_mode,
    mavlink.MAV_CMD_DO_REPOSITION: command_do_reposition,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH: command_nav_return_to_launch,
    mavlink.MAV_CMD_MISSION_START: command_mission_start,
    mavlink.MAV_CMD_DO_SET_MISSION_CURRENT: command_do_set_mission_current,
    mavlink.MAV_CMD_DO_CHANGE_SPEED: command_do_change_speed,
    mavlink.MAV_CMD_REQUEST_MESSAGE: command_request_message,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: command_request_autopilot_capabilities,
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: command_set_message_interval,
    mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: command_get_message_interval,
    mavlink.MAV_CMD_DO_SET_HOME: command_do_set_home,
}


def command_image_start_capture(v: Vehicle, c: CommandArgs) -> Result:
    """Engagement request (docs/mavlink.md): resolved against ground truth at the vehicle's
    position; param4 is the engagement sequence number, a repeat replays its first outcome."""
    sequence = engagement_sequence(c.p2, c.p3, c.p4)
    if sequence is None:
        v.host.stats.rejected_commands += 1
        return mavlink.MAV_RESULT_DENIED
    outcome, replay = v.engagements.resolve(sequence, lambda: v.host.engage(v.index))
    v.ack(
        c.command,
        mavlink.MAV_RESULT_ACCEPTED,
        c.peer,
        progress=sequence % 256,  # result_param1: which request this answers
        result_param2=outcome.target_id,
        from_camera=True,
    )
    if not replay:
        v.send_from_camera(
            mavlink.MAVLink_statustext_message(
                mavlink.MAV_SEVERITY_INFO, engagement_text(sequence, outcome).encode()
            )
        )
    return -1


CAMERA_COMMANDS: dict[int, CommandHandler] = {
    mavlink.MAV_CMD_IMAGE_START_CAPTURE: command_image_start_capture,
}


def run_command(v: Vehicle, c: CommandArgs, table: dict[int, CommandHandler]) -> Result:
    """Run a command and return its result (-1 when the handler already sent the ACK)."""
    handler = table.get(c.command)
    if handler is None:
        return mavlink.MAV_RESULT_UNSUPPORTED
    return handler(v, c)
