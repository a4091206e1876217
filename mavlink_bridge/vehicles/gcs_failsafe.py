"""The vehicles' ground-station failsafe, set by the daemon at launch (before arming).

What an ArduPlane does when it stops hearing its ground station (``Plane::check_long_failsafe``,
``Plane::failsafe_long_on_event``; the simulator does the same, sim_gateway/failsafe.py): with
``FS_GCS_ENABL`` 1, after ``FS_LONG_TIMEOUT`` seconds without a HEARTBEAT from its GCS (system
id ``MAV_GCS_SYSID``/``SYSID_MYGCS``, 255 by default: the daemon's), it takes the long failsafe
action ``FS_LONG_ACTN``; in GUIDED, 0 (*Continue*) keeps GUIDED, so the plane flies on to its
last guided target and circles it, 1 returns home (RTL: a straight line that may cross a threat
zone), 2 glides. ``FS_SHORT_ACTN`` acts on a lost RC link only (in GUIDED, 0 changes nothing;
1 would switch to CIRCLE where the plane is).

The daemon's choice, ``autopilot_adapter.MISSION_FAILSAFE``: heartbeat failsafe on, *Continue*.
Every guided target the flight envelope sends keeps its loiter circle clear of every threat
(``flight_envelope.py``), so a plane whose ground station is gone, for any length of time,
circles a place proven safe instead of flying a line home through a threat (issue 12, finding 2:
a failsafe that switched planes to CIRCLE where they were took two into threat zones). The
envelope also keeps the circle a plane would fly where it is (CIRCLE, ``FS_SHORT_ACTN`` 1 on an
RC loss, or a vehicle that refused these settings) clear for the coming decision period. Short
action 0 leaves GUIDED alone on an RC loss; the long timeout only says when the vehicle reports
the failsafe (it changes nothing in GUIDED with *Continue*).

Parameters are set with PARAM_SET and confirmed by the PARAM_VALUE the vehicle answers with;
unanswered ones are resent every half second, for up to 20 s (a set and its answer both get
through a link losing 30 % each way in half the tries, so 12 tries left about one launch of
ten planes in 80 unconfirmed; 40 leave one parameter in 10^5 at 50 % loss each way). A vehicle that
refuses (answers another value) or never answers fails the launch with a line naming it and
the fix.
"""

from __future__ import annotations

from collections.abc import Sequence

from mavlink_bridge.vehicles.autopilot_adapter import autopilot_for
from mavlink_bridge.vehicles.param_encoding import encode_param
from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_wire.protocol import AUTOPILOT_COMPONENT_ID
from planner.errors import UserError


def set_gcs_failsafe(
    link: SwarmLink,
    vehicles: Sequence[VehicleState],
    retry_s: float = 0.5,
    attempts: int = 40,
) -> None:
    """Set every vehicle's GCS-loss settings, its autopilot's (``autopilot_adapter.py``:
    ArduPlane's :data:`~autopilot_adapter.MISSION_FAILSAFE`, PX4's NAV_DLL_ACT and geofence
    settings), and wait until each confirms every value."""
    todo = {
        (v.key, name): (v, value, ptype)
        for v in vehicles
        for name, value, ptype in autopilot_for(v).failsafe_parameters()
    }

    def confirmed(v: VehicleState, name: str, value: float) -> bool:
        got = v.params.get(name)
        return got is not None and abs(got - value) <= 1e-3 * max(1.0, abs(value))

    for (_, name), (v, _, _) in todo.items():
        v.params.pop(name, None)  # only an answer to our PARAM_SET counts
    # our heartbeat first, on the same links: an autopilot that has not heard its ground
    # station yet takes the failsafe the moment it is enabled (ArduPlane SITL V4.8.0-dev, a node
    # that reached the launch within 0.1 s of hearing its long-booted plane: "GCS Failsafe On:
    # switched to RTL" on the ground, then "PreArm: RTL mode not armable")
    link.send_heartbeat()
    for _ in range(attempts):
        for (_, name), (v, value, ptype) in todo.items():
            if not v.lost:
                wire = encode_param(v.autopilot, value, ptype)
                v.link.mav.param_set_send(
                    v.system_id, AUTOPILOT_COMPONENT_ID, name.encode(), wire, ptype
                )
        waiting = [(v, name) for (_, name), (v, _, _) in todo.items()]
        link.pump_until(lambda w=waiting: all(name in v.params for v, name in w), retry_s)
        todo = {
            key: entry for key, entry in todo.items() if not confirmed(entry[0], key[1], entry[1])
        }
        refused = [(key, entry) for key, entry in todo.items() if key[1] in entry[0].params]
        if refused:
            (sysid, name), (v, value, _) = refused[0]
            fix = autopilot_for(v).failsafe_fix
            raise UserError(
                f"vehicle {sysid} kept {name} = {v.params[name]:g} when set to {value:g}; its "
                f"GCS failsafe must fly on to the last guided target ({fix}): set them by "
                f"hand or check its parameter limits"
            )
        if not todo:
            return
    (sysid, name), _ = next(iter(todo.items()))
    raise UserError(
        f"vehicle {sysid} did not confirm {name} (PARAM_VALUE) after {attempts} tries; check "
        f"that it accepts PARAM_SET from system id 255 over this link"
    )
