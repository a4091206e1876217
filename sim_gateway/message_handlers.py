"""What a simulated vehicle does with each MAVLink message addressed to it: one small handler
per message type, and :data:`HANDLERS`, the table the simulator dispatches on.

Addressing: a message with a target_system is handled only by that vehicle (0: every vehicle);
target_component 0 or 1 reaches the autopilot, 100 the camera, any other is ignored (as a real
vehicle has no such component). Messages without a target (HEARTBEAT) go to every vehicle.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_gateway import flight_modes as modes
from sim_gateway.commands import CAMERA_COMMANDS, COMMANDS, CommandArgs, run_command
from sim_gateway.mavlink_endpoint import MAV_COMP_ID_AUTOPILOT1, MAV_COMP_ID_CAMERA, peer_of
from sim_gateway.mission_protocol import (
    handle_mission_ack,
    handle_mission_clear_all,
    handle_mission_count,
    handle_mission_item,
    handle_mission_item_int,
    handle_mission_request,
    handle_mission_request_int,
    handle_mission_request_list,
    handle_mission_set_current,
)
from sim_gateway.mission_store import RELATIVE_FRAMES
from sim_gateway.parameter_protocol import (
    handle_param_request_list,
    handle_param_request_read,
    handle_param_set,
)
from sim_gateway.telemetry_streams import DATA_STREAMS
from sim_gateway.vehicle import Vehicle

FTP_OPCODE_NAK = 129
FTP_ERROR_UNKNOWN_COMMAND = 7  # MAV_FTP_ERR_UNKNOWNCOMMAND: FTP is off on this vehicle


def handle_heartbeat(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    """Any heartbeat from a system that is not a simulated vehicle is a ground station."""
    v.on_gcs_heartbeat(v.host.wall_s())


#: A command whose sequence number is at most this far behind the sender's newest one, within
#: REORDER_WINDOW_S, was overtaken on the way (a reordering link); further back it is a sender
#: that restarted its counter (e.g. a restarted daemon), which is applied.
REORDER_SEQ_WINDOW = 32
REORDER_WINDOW_S = 2.0


def overtaken(v: Vehicle, msg: mavlink.MAVLink_message) -> bool:
    """True (and counted) if a newer command of the same sender was applied already.

    MAVLink 2 gives every sender one 8-bit sequence counter per link, so a command that
    arrives after a newer one from the same sender has a slightly smaller number. Applying it
    would send the vehicle back to a stale target or mode; it is dropped without an ACK (the
    sender has stopped waiting for it). Duplicates of one frame are filtered earlier."""
    peer, seq, now = peer_of(msg), msg.get_seq(), v.host.wall_s()
    last = v.last_command.get(peer)
    if last is not None and now - last[1] < REORDER_WINDOW_S:
        behind = (last[0] - seq) % 256
        if 0 < behind <= REORDER_SEQ_WINDOW:
            v.host.stats.stale_commands += 1
            return True
    v.last_command[peer] = (seq, now)
    return False


def _dispatch_command(v: Vehicle, msg: mavlink.MAVLink_message, args: CommandArgs) -> None:
    if overtaken(v, msg):
        return
    if msg.target_component in (0, MAV_COMP_ID_AUTOPILOT1):
        table = COMMANDS
    elif msg.target_component == MAV_COMP_ID_CAMERA:
        table = CAMERA_COMMANDS
    else:
        v.host.stats.ignored_messages += 1
        return
    result = run_command(v, args, table)
    if result == mavlink.MAV_RESULT_UNSUPPORTED:
        v.host.stats.rejected_commands += 1
    if result >= 0:
        v.ack(args.command, result, args.peer, from_camera=table is CAMERA_COMMANDS)


def handle_command_long(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
    _dispatch_command(v, msg, CommandArgs(msg.command, params, peer_of(msg), as_int=False))


def handle_command_int(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x / 1e7, msg.y / 1e7, msg.z)
    args = CommandArgs(
        msg.command, params, peer_of(msg), as_int=True, frame=msg.frame, x=msg.x, y=msg.y
    )
    _dispatch_command(v, msg, args)


def handle_set_mode(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    if overtaken(v, msg):
        return
    ok = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED) and v.set_mode(
        msg.custom_mode
    )
    if not ok:
        v.host.stats.rejected_commands += 1
    # ArduPilot acknowledges SET_MODE with a COMMAND_ACK whose command is the message id (11)
    v.ack(
        mavlink.MAVLINK_MSG_ID_SET_MODE,
        mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_FAILED,
        peer_of(msg),
    )


def handle_request_data_stream(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    names = DATA_STREAMS.get(msg.req_stream_id)
    if names is None:
        return  # a group whose messages this vehicle does not have (RAW_SENSORS, RC_CHANNELS)
    rate = msg.req_message_rate if msg.start_stop else 0
    for name in names:
        v.streams.set_rate_hz(name, rate)


def handle_set_position_target_global_int(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    """ArduPlane in GUIDED takes only the altitude from this message (lat/lon are ignored)."""
    ignore_alt = msg.type_mask & mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE
    if v.mode != modes.GUIDED or ignore_alt or not math.isfinite(msg.alt):
        return
    alt = msg.alt if msg.coordinate_frame in RELATIVE_FRAMES else msg.alt - v.host.home_amsl_m()
    v.fleet.target_alt_m[v.index] = alt
    if v.guided is not None:
        v.guided.alt_m = alt


def handle_file_transfer_protocol(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    """MAVLink FTP is not offered: NAK every request so clients (MAVProxy) fall back at once."""
    payload = bytearray(msg.payload)
    seq = int.from_bytes(payload[0:2], "little")
    reply = bytearray(251)
    reply[0:2] = ((seq + 1) % 65536).to_bytes(2, "little")
    reply[2] = payload[2]  # session
    reply[3] = FTP_OPCODE_NAK
    reply[4] = 1  # size of data
    reply[5] = payload[3]  # req_opcode
    reply[12] = FTP_ERROR_UNKNOWN_COMMAND
    peer = peer_of(msg)
    v.send(mavlink.MAVLink_file_transfer_protocol_message(0, peer[0], peer[1], list(reply)))


def handle_timesync(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    if msg.tc1 == 0:
        now_ns = int(v.host.wall_s() * 1e9)
        v.send(mavlink.MAVLink_timesync_message(now_ns, msg.ts1))


def handle_system_time(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    """A ground station's clock (SYSTEM_TIME with UTC), which a simulated vehicle has no use for.
    One without UTC (time_unix_usec 0) is a lockstep grant: the simulator judges who sent it
    before any vehicle sees it (``Inbox.lockstep_grant``, sim_gateway/inbox.py and lockstep.py)."""


Handler = Callable[[Vehicle, mavlink.MAVLink_message], None]

HANDLERS: dict[str, Handler] = {
    "HEARTBEAT": handle_heartbeat,
    "COMMAND_LONG": handle_command_long,
    "COMMAND_INT": handle_command_int,
    "SET_MODE": handle_set_mode,
    "REQUEST_DATA_STREAM": handle_request_data_stream,
    "SET_POSITION_TARGET_GLOBAL_INT": handle_set_position_target_global_int,
    "FILE_TRANSFER_PROTOCOL": handle_file_transfer_protocol,
    "TIMESYNC": handle_timesync,
    "SYSTEM_TIME": handle_system_time,
    "PARAM_REQUEST_LIST": handle_param_request_list,
    "PARAM_REQUEST_READ": handle_param_request_read,
    "PARAM_SET": handle_param_set,
    "MISSION_COUNT": handle_mission_count,
    "MISSION_ITEM_INT": handle_mission_item_int,
    "MISSION_ITEM": handle_mission_item,
    "MISSION_ACK": handle_mission_ack,
    "MISSION_REQUEST_LIST": handle_mission_request_list,
    "MISSION_REQUEST_INT": handle_mission_request_int,
    "MISSION_REQUEST": handle_mission_request,
    "MISSION_CLEAR_ALL": handle_mission_clear_all,
    "MISSION_SET_CURRENT": handle_mission_set_current,
}

#: Messages whose target_component must be the autopilot (0 or 1) to be handled.
AUTOPILOT_ONLY = frozenset(HANDLERS) - {
    "HEARTBEAT",
    "COMMAND_LONG",
    "COMMAND_INT",
    "SET_MODE",
    "TIMESYNC",
    "SYSTEM_TIME",
}
