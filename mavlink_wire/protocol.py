"""The MAVLink dialect the bridge speaks, and the numbers it uses from it.

pymavlink chooses MAVLink 1 or 2 once per process, when it is first imported, from the
``MAVLINK20`` environment variable; this module sets it before importing, so every other module
of the bridge imports pymavlink through here.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

#: Our own identity on the link: a ground station (255 / MAV_COMP_ID_MISSIONPLANNER).
GCS_SYSTEM_ID = 255
GCS_COMPONENT_ID = mavlink.MAV_COMP_ID_MISSIONPLANNER

#: A vehicle's autopilot is component 1; its camera (looks and engagements) is component 100.
AUTOPILOT_COMPONENT_ID = 1
CAMERA_COMPONENT_ID = mavlink.MAV_COMP_ID_CAMERA

#: ArduPlane custom modes (the ones the daemon uses).
PLANE_MODE_AUTO = 10
PLANE_MODE_RTL = 11
PLANE_MODE_LOITER = 12
PLANE_MODE_TAKEOFF = 13
PLANE_MODE_GUIDED = 15

PLANE_MODE_NAMES = {
    0: "MANUAL",
    1: "CIRCLE",
    2: "STABILIZE",
    5: "FBWA",
    6: "FBWB",
    10: "AUTO",
    11: "RTL",
    12: "LOITER",
    13: "TAKEOFF",
    15: "GUIDED",
}


def enum_name(enum: str, value: int) -> str:
    """The symbolic name of an enum value (e.g. ``MAV_RESULT_DENIED``), or the number."""
    entry = mavlink.enums.get(enum, {}).get(value)
    return entry.name if entry is not None else str(value)


def result_name(result: int) -> str:
    """``MAV_RESULT_*`` name of a COMMAND_ACK result."""
    return enum_name("MAV_RESULT", result)


def command_name(command: int) -> str:
    """``MAV_CMD_*`` name of a command id."""
    return enum_name("MAV_CMD", command)


def mode_name(custom_mode: int) -> str:
    """ArduPlane name of a custom mode."""
    return PLANE_MODE_NAMES.get(custom_mode, f"mode {custom_mode}")


__all__ = [
    "mavlink",
    "GCS_SYSTEM_ID",
    "GCS_COMPONENT_ID",
    "AUTOPILOT_COMPONENT_ID",
    "CAMERA_COMPONENT_ID",
    "result_name",
    "command_name",
    "mode_name",
    "enum_name",
]


def component_heartbeat(mav: mavlink.MAVLink, mav_type: int) -> bytes:
    """The HEARTBEAT of a component that is no autopilot (a camera, a radio relay), packed as
    ``mav``'s: active, MAVLink version 3, ``MAV_AUTOPILOT_INVALID``."""
    msg = mavlink.MAVLink_heartbeat_message(
        mav_type, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3
    )
    return bytes(msg.pack(mav))
