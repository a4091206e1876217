"""Uploading the threat zones as a geofence (MAVLink mission protocol, mission_type FENCE).

Each threat zone becomes one MISSION_ITEM_INT ``MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION`` (param1 =
radius in metres, x/y = centre lat/lon * 1e7), so the autopilot itself can keep out of it.
The exchange, run for every vehicle at once: MISSION_COUNT -> the vehicle asks for each item
(MISSION_REQUEST_INT, or the legacy MISSION_REQUEST that ArduPilot still sends; both answered
with MISSION_ITEM_INT) -> MISSION_ACK. A vehicle that does not ask within the retry interval gets
the MISSION_COUNT again.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from mavlink_bridge.protocol import AUTOPILOT_COMPONENT_ID, enum_name, mavlink
from mavlink_bridge.swarm_link import SwarmLink
from mavlink_bridge.vehicle_state import VehicleState
from planner.errors import UserError


class MissionUploadError(UserError):
    """A vehicle refused or never completed an upload."""


@dataclass(frozen=True)
class FenceCircle:
    """An exclusion circle: centre (degrees) and radius (metres)."""

    lat_deg: float
    lon_deg: float
    radius_m: float


def send_fence_item(vehicle: VehicleState, seq: int, circle: FenceCircle) -> None:
    """MISSION_ITEM_INT of one exclusion circle (frame GLOBAL, as QGroundControl sends it)."""
    vehicle.link.mav.mission_item_int_send(
        vehicle.system_id,
        AUTOPILOT_COMPONENT_ID,
        seq,
        mavlink.MAV_FRAME_GLOBAL,
        mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION,
        0,
        1,
        circle.radius_m,
        0,
        0,
        0,
        round(circle.lat_deg * 1e7),
        round(circle.lon_deg * 1e7),
        0.0,
        mavlink.MAV_MISSION_TYPE_FENCE,
    )


def upload_fence(
    link: SwarmLink,
    vehicles: list[VehicleState],
    circles: list[FenceCircle],
    timeout_s: float = 20.0,
    retry_interval_s: float = 1.0,
) -> None:
    """Upload the same exclusion circles to every vehicle; raises MissionUploadError naming the
    vehicle and the MAV_MISSION_RESULT when one refuses, or when one never finishes."""
    fence = mavlink.MAV_MISSION_TYPE_FENCE
    done: dict[int, int | None] = {v.system_id: None for v in vehicles}  # sysid -> ack result
    last_count: dict[int, float] = {}

    def send_count(vehicle: VehicleState) -> None:
        vehicle.mission_requests.clear()
        vehicle.mission_ack = None
        vehicle.link.mav.mission_count_send(
            vehicle.system_id, AUTOPILOT_COMPONENT_ID, len(circles), fence
        )
        last_count[vehicle.system_id] = time.monotonic()

    for vehicle in vehicles:
        send_count(vehicle)
    last_progress = {v.system_id: time.monotonic() for v in vehicles}
    deadline = time.monotonic() + timeout_s
    while any(result is None for result in done.values()):
        if time.monotonic() > deadline:
            stuck = [str(s) for s, r in done.items() if r is None]
            raise MissionUploadError(
                f"fence upload to vehicle {', '.join(stuck)} did not complete "
                f"within {timeout_s:g} s; "
                f"check the link (and that the autopilot supports MISSION_TYPE_FENCE)"
            )
        link.pump(0.01)
        now = time.monotonic()
        for vehicle in vehicles:
            sysid = vehicle.system_id
            if done[sysid] is not None:
                continue
            while vehicle.mission_requests:
                seq, mission_type = vehicle.mission_requests.popleft()
                if mission_type == fence and 0 <= seq < len(circles):
                    send_fence_item(vehicle, seq, circles[seq])
                    last_progress[sysid] = now
            if vehicle.mission_ack is not None and vehicle.mission_ack[1] == fence:
                done[sysid] = vehicle.mission_ack[0]
            elif (
                now - last_progress[sysid] > retry_interval_s
                and now - last_count[sysid] > retry_interval_s
            ):
                send_count(vehicle)  # nothing asked for a while: start again
                last_progress[sysid] = now
    for sysid, result in done.items():
        if result != mavlink.MAV_MISSION_ACCEPTED:
            raise MissionUploadError(
                f"vehicle {sysid} refused the fence upload: "
                f"{enum_name('MAV_MISSION_RESULT', result or 0)}"
                f" (an autopilot still initialising answers NO_SPACE; wait for STANDBY)"
            )
