"""The MAVLink parameter protocol on the vehicle side: PARAM_REQUEST_LIST, PARAM_REQUEST_READ,
PARAM_SET (answered with PARAM_VALUE; a refused value is answered with the unchanged value and a
STATUSTEXT, the protocol's way to say no). Values travel as floats holding the number itself
(ArduPilot's convention, not PX4's byte-wise packing).
"""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_gateway.vehicle import Vehicle


def _param_id(raw: str | bytes) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", errors="replace")
    return raw.split("\x00", 1)[0]


def send_param_value(v: Vehicle, name: str) -> None:
    v.send(
        mavlink.MAVLink_param_value_message(
            name.encode(),
            float(v.params[name]),
            v.params.ptype(name),
            len(v.params),
            v.params.index(name),
        )
    )


def handle_param_request_list(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    for name in v.params.names():
        send_param_value(v, name)


def handle_param_request_read(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    name = v.params.name_at(msg.param_index) if msg.param_index >= 0 else _param_id(msg.param_id)
    if name is None or name not in v.params:
        v.host.stats.rejected_commands += 1
        return  # ArduPilot stays silent about unknown parameters
    send_param_value(v, name)


def handle_param_set(v: Vehicle, msg: mavlink.MAVLink_message) -> None:
    name = _param_id(msg.param_id)
    if name not in v.params:
        v.host.stats.rejected_commands += 1
        return
    refused = v.params.set(name, float(msg.param_value))
    if refused:
        v.host.stats.rejected_commands += 1
        v.statustext(f"Param {refused}"[:50], mavlink.MAV_SEVERITY_WARNING)
    else:
        v.apply_params(changed=name)
    send_param_value(v, name)
