"""How a parameter's value travels in PARAM_SET / PARAM_VALUE (a float field), by autopilot.

ArduPilot sends every value as the float of its number (C-style cast). PX4 sends an integer
parameter (MAV_PARAM_TYPE_INT32) as the four bytes of the int32 in the float field (bytewise
encoding): a 1.0 sent for PX4's INT32 COM_DL_LOSS_T set it to 1065353216 (measured, PX4 SITL).
"""

from __future__ import annotations

import struct

from mavlink_wire.protocol import mavlink

REAL32 = mavlink.MAV_PARAM_TYPE_REAL32


def bytewise(autopilot: int) -> bool:
    """The autopilot encodes integer parameters bytewise (PX4)."""
    return autopilot == mavlink.MAV_AUTOPILOT_PX4


def encode_param(autopilot: int, value: float, ptype: int) -> float:
    """PARAM_SET's param_value for ``value`` of MAVLink type ``ptype``."""
    if not bytewise(autopilot) or ptype == REAL32:
        return value
    return struct.unpack("<f", struct.pack("<i", round(value)))[0]


def decode_param(autopilot: int, value: float, ptype: int) -> float:
    """A PARAM_VALUE's param_value as the parameter's number."""
    if not bytewise(autopilot) or ptype == REAL32:
        return value
    return float(struct.unpack("<i", struct.pack("<f", value))[0])
