"""The MAVLink mission protocol on the vehicle side, both ways, for mission types 0 (mission),
1 (fence) and 2 (rally): one handler per message.

Upload (GCS -> vehicle): MISSION_COUNT, then the vehicle asks for each item with the legacy
MISSION_REQUEST (as ArduPlane does; a client that answers MISSION_ACK UNSUPPORTED to it, such as
MAVSDK, is asked again with MISSION_REQUEST_INT), accepts MISSION_ITEM_INT or MISSION_ITEM, and
ends with MISSION_ACK. During the boot phase an upload is refused with MISSION_ACK NO_SPACE, as
ArduPlane SITL does before its EKF is ready. Download: MISSION_REQUEST_LIST -> MISSION_COUNT,
MISSION_REQUEST_INT / MISSION_REQUEST -> MISSION_ITEM_INT / MISSION_ITEM; item 0 of a mission is
the home position.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_gateway import flight_modes as modes
from sim_gateway.mavlink_endpoint import peer_of
from sim_gateway.mission_store import (
    FENCE,
    MAX_ITEMS,
    MISSION,
    MISSION_TYPES,
    MissionItem,
    UploadTransfer,
    validate_item,
)
from sim_gateway.vehicle import Vehicle

UPLOAD_RETRY_WALL_S = 0.5
UPLOAD_MAX_RETRIES = 8


def _mission_ack(v: Vehicle, peer: tuple[int, int], result: int, mission_type: int) -> None:
    v.send(mavlink.MAVLink_mission_ack_message(peer[0], peer[1], result, mission_type=mission_type))


def _mission_type(v: Vehicle, msg: mavlink.MAVLink_message) -> int | None:
    mission_type = getattr(msg, "mission_type", 0)
    if mission_type not in MISSION_TYPES:
        v.host.stats.rejected_commands += 1
        return None
    return mission_type


# ---------------------------------------------------------------------- upload


def request_next_item(v: Vehicle, transfer: UploadTransfer) -> None:
    peer, seq = transfer.peer, transfer.next_seq
    if transfer.use_request_int:
        message = mavlink.MAVLink_mission_request_int_message(
            peer[0], peer[1], seq, transfer.mission_type
        )
    else:
        message = mavlink.MAVLink_mission_request_message(
            peer[0], peer[1], seq, transfer.mission_type
        )
    transfer.last_request_wall_s = v.host.wall_s()
    v.send(message)


def handle_mission_count(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    mission_type = _mission_type(v, msg)
    if mission_type is None:
        _mission_ack(v, peer_of(msg), mavlink.MAV_MISSION_INVALID, getattr(msg, "mission_type", 0))
        return
    if v.booting:
        _mission_ack(v, peer_of(msg), mavlink.MAV_MISSION_NO_SPACE, mission_type)
        return
    if msg.count > MAX_ITEMS:
        _mission_ack(v, peer_of(msg), mavlink.MAV_MISSION_NO_SPACE, mission_type)
        return
    if msg.count == 0:
        store_items(v, mission_type, [])
        _mission_ack(v, peer_of(msg), mavlink.MAV_MISSION_ACCEPTED, mission_type)
        return
    v.missions.upload = UploadTransfer(mission_type, msg.count, peer_of(msg))
    request_next_item(v, v.missions.upload)


def _item_from_message(
    msg: mavlink.MAVLink_message, as_int: bool, mission_type: int
) -> MissionItem:
    if as_int:
        x, y = int(msg.x), int(msg.y)
    else:
        x = round(msg.x * 1e7) if math.isfinite(msg.x) else 2**31 - 1
        y = round(msg.y * 1e7) if math.isfinite(msg.y) else 2**31 - 1
    return MissionItem(
        msg.seq,
        msg.frame,
        msg.command,
        msg.current,
        msg.autocontinue,
        msg.param1,
        msg.param2,
        msg.param3,
        msg.param4,
        x,
        y,
        float(msg.z),
        mission_type,
    )


def _receive_item(v: Vehicle, msg: mavlink.MAVLink_message, as_int: bool) -> None:
    transfer = v.missions.upload
    mission_type = getattr(msg, "mission_type", 0)
    if transfer is None or transfer.mission_type != mission_type or peer_of(msg) != transfer.peer:
        v.host.stats.ignored_messages += 1
        return
    if msg.seq != transfer.next_seq:
        request_next_item(v, transfer)  # out of order: ask again for the one we need
        return
    item = _item_from_message(msg, as_int, mission_type)
    result = validate_item(item)
    if result != mavlink.MAV_MISSION_ACCEPTED:
        v.missions.upload = None
        v.host.stats.rejected_commands += 1
        _mission_ack(v, transfer.peer, result, mission_type)
        return
    transfer.items.append(item)
    transfer.retries = 0
    if transfer.complete:
        v.missions.upload = None
        store_items(v, mission_type, transfer.items)
        _mission_ack(v, transfer.peer, mavlink.MAV_MISSION_ACCEPTED, mission_type)
    else:
        request_next_item(v, transfer)


def handle_mission_item_int(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    _receive_item(v, msg, as_int=True)


def handle_mission_item(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    _receive_item(v, msg, as_int=False)


def store_items(v: Vehicle, mission_type: int, items: list[MissionItem]) -> None:
    was_auto = v.mode == modes.AUTO
    v.missions.replace(mission_type, items)
    if mission_type == FENCE:
        v.fence_items_changed()
    if mission_type == MISSION:
        v.jumps_left.clear()
        if was_auto and len(items) < 2:
            v.set_mode(modes.LOITER, "Mission cleared")
        v.send_mission_current()


def handle_mission_ack(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    """A NAK of our legacy MISSION_REQUEST means the uploader wants MISSION_REQUEST_INT."""
    transfer = v.missions.upload
    if transfer is None or peer_of(msg) != transfer.peer:
        return  # the ACK that ends a download, or a stray one
    if msg.type == mavlink.MAV_MISSION_UNSUPPORTED and not transfer.use_request_int:
        transfer.use_request_int = True
        request_next_item(v, transfer)
    elif msg.type != mavlink.MAV_MISSION_ACCEPTED:
        v.missions.upload = None  # the uploader gave up


def retry_upload(v: Vehicle, now_wall_s: float) -> None:
    """Ask again for an item that did not come; give up after a few tries (as ArduPilot)."""
    transfer = v.missions.upload
    if transfer is None or now_wall_s - transfer.last_request_wall_s < UPLOAD_RETRY_WALL_S:
        return
    transfer.retries += 1
    if transfer.retries > UPLOAD_MAX_RETRIES:
        v.missions.upload = None
        _mission_ack(
            v, transfer.peer, mavlink.MAV_MISSION_OPERATION_CANCELLED, transfer.mission_type
        )
        return
    request_next_item(v, transfer)


# ---------------------------------------------------------------------- download


def handle_mission_request_list(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    mission_type = _mission_type(v, msg)
    if mission_type is None:
        return
    count = v.missions.count(mission_type)
    if mission_type == MISSION:
        count = max(count, 1)  # item 0, home, is always there
    peer = peer_of(msg)
    v.send(mavlink.MAVLink_mission_count_message(peer[0], peer[1], count, mission_type))


def _stored_item(v: Vehicle, mission_type: int, seq: int) -> MissionItem | None:
    items = v.missions.items[mission_type]
    if mission_type == MISSION and seq == 0:
        lat, lon = v.host.local_to_geodetic(v.home_x_m, v.home_y_m)
        return MissionItem(
            0,
            mavlink.MAV_FRAME_GLOBAL_INT,
            mavlink.MAV_CMD_NAV_WAYPOINT,
            0,
            1,
            0,
            0,
            0,
            0,
            round(lat * 1e7),
            round(lon * 1e7),
            v.host.home_amsl_m(),
            MISSION,
        )
    return items[seq] if 0 <= seq < len(items) else None


def _send_item(v: Vehicle, msg: mavlink.MAVLink_message, as_int: bool) -> None:
    mission_type = _mission_type(v, msg)
    if mission_type is None:
        return
    peer = peer_of(msg)
    item = _stored_item(v, mission_type, msg.seq)
    if item is None:
        v.host.stats.rejected_commands += 1
        _mission_ack(v, peer, mavlink.MAV_MISSION_INVALID_SEQUENCE, mission_type)
        return
    current = int(mission_type == MISSION and item.seq == v.missions.current_seq)
    # MISSION_ITEM_INT carries degE7 integers; the legacy MISSION_ITEM carries degrees.
    message = (
        mavlink.MAVLink_mission_item_int_message if as_int else mavlink.MAVLink_mission_item_message
    )
    scale = 1 if as_int else 1e-7
    out = message(
        peer[0], peer[1], item.seq, item.frame, item.command, current, item.autocontinue,
        item.param1, item.param2, item.param3, item.param4, item.x * scale, item.y * scale, item.z,
        mission_type,
    )  # fmt: skip
    v.send(out)


def handle_mission_request_int(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    _send_item(v, msg, as_int=True)


def handle_mission_request(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    _send_item(v, msg, as_int=False)


# ---------------------------------------------------------------------- other


def handle_mission_clear_all(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    mission_type = getattr(msg, "mission_type", 0)
    if mission_type == mavlink.MAV_MISSION_TYPE_ALL:
        for t in MISSION_TYPES:
            store_items(v, t, [])
    elif mission_type in MISSION_TYPES:
        store_items(v, mission_type, [])
    else:
        v.host.stats.rejected_commands += 1
        _mission_ack(v, peer_of(msg), mavlink.MAV_MISSION_INVALID, mission_type)
        return
    _mission_ack(v, peer_of(msg), mavlink.MAV_MISSION_ACCEPTED, mission_type)


def handle_mission_set_current(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    if not v.set_current_item(msg.seq):
        v.host.stats.rejected_commands += 1
