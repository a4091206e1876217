"""Uploading the threat zones as a geofence (MAVLink mission protocol, mission_type FENCE).

Each threat zone becomes one MISSION_ITEM_INT ``MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION`` (param1 =
radius in metres, x/y = centre lat/lon * 1e7), so the autopilot itself can keep out of it.
The exchange, run for every vehicle at once: MISSION_COUNT -> the vehicle asks for each item
(MISSION_REQUEST_INT, or the legacy MISSION_REQUEST that ArduPilot still sends; both answered
with MISSION_ITEM_INT) -> MISSION_ACK. Lost datagrams are sent again by the side that waits
(``upload_fence``), as the mission protocol's retries do.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from mavlink_bridge.protocol import AUTOPILOT_COMPONENT_ID, enum_name, mavlink
from mavlink_bridge.swarm_link import SwarmLink
from mavlink_bridge.vehicle_state import VehicleState
from planner.errors import UserError

#: uploads begun (MISSION_COUNT sent after the vehicle had asked for items) before a vehicle
#: that keeps asking but never acknowledges counts as failed
MAX_RESTARTS = 20
#: the item a vehicle asked for last is sent again this many times (every retry interval) with
#: no answer before the upload starts over (``upload_fence``)
ITEM_RESENDS = 3


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
    stall_timeout_s: float = 20.0,
    retry_interval_s: float = 0.5,
) -> None:
    """Upload the same exclusion circles to every vehicle; raises MissionUploadError naming the
    vehicle and the MAV_MISSION_RESULT when one refuses, or when one stops answering.

    Over a lossy link each side re-sends what the other did not answer (the mission protocol's
    retries), and nothing that got through is thrown away: every ``retry_interval_s`` without
    an answer the daemon sends again what the vehicle last went without (MISSION_COUNT until it
    asks for an item; then the item it asked for last, ``ITEM_RESENDS`` times; after the last
    item, or when the vehicle stays silent through those resends, the MISSION_COUNT again:
    only a new upload brings back a MISSION_ACK that was lost, and a vehicle whose transfer
    ended ignores items. On a link that duplicates and delays, a late MISSION_COUNT restarted a
    vehicle's transfer after it had asked for item 1, a delayed item 1 then completed it, its
    ACK was lost, and item 0 was resent to a vehicle that no longer listened until the upload
    stalled: the reliability bench at 30 % loss). A vehicle gives up
    only when it has said nothing of this upload for ``stall_timeout_s`` (a dead link, an
    autopilot without MISSION_TYPE_FENCE), not after a fixed time: a link that loses 30 % each
    way gets its fence through (before, every stall restarted the whole exchange and the upload
    gave up after 20 s in 2 of 3 runs)."""
    fence = mavlink.MAV_MISSION_TYPE_FENCE
    n = len(circles)
    done: dict[int, int | None] = {v.system_id: None for v in vehicles}  # sysid -> ack result
    last_asked: dict[int, int | None] = {}  # the item each vehicle asked for last (this upload)
    last_sent: dict[int, float] = {}
    heard: dict[int, float] = {}  # the vehicle's last message of this upload
    restarts = dict.fromkeys(done, 0)
    resends = dict.fromkeys(done, 0)  # the last asked item sent again with no answer since

    def send_count(vehicle: VehicleState) -> None:
        vehicle.mission_requests.clear()
        vehicle.mission_ack = None
        vehicle.link.mav.mission_count_send(vehicle.system_id, AUTOPILOT_COMPONENT_ID, n, fence)
        last_asked[vehicle.system_id] = None
        last_sent[vehicle.system_id] = time.monotonic()

    for vehicle in vehicles:
        send_count(vehicle)
        heard[vehicle.system_id] = time.monotonic()
    while any(result is None for result in done.values()):
        link.pump(0.01)
        now = time.monotonic()
        for vehicle in vehicles:
            sysid = vehicle.system_id
            if done[sysid] is not None:
                continue
            while vehicle.mission_requests:
                seq, mission_type = vehicle.mission_requests.popleft()
                if mission_type == fence and 0 <= seq < n:
                    send_fence_item(vehicle, seq, circles[seq])
                    last_asked[sysid], last_sent[sysid], heard[sysid] = seq, now, now
                    resends[sysid] = 0
            if vehicle.mission_ack is not None and vehicle.mission_ack[1] == fence:
                done[sysid] = vehicle.mission_ack[0]
                continue
            if now - heard[sysid] > stall_timeout_s:
                raise MissionUploadError(
                    f"fence upload to vehicle {sysid} stalled: nothing of it heard for "
                    f"{stall_timeout_s:g} s; check the link (and that the autopilot supports "
                    f"MISSION_TYPE_FENCE)"
                )
            if now - last_sent[sysid] > retry_interval_s:
                asked = last_asked[sysid]
                if asked is None or asked == n - 1 or resends[sysid] >= ITEM_RESENDS:
                    # not started, its MISSION_ACK lost, or its transfer over: from the start
                    restarts[sysid] += asked is not None
                    resends[sysid] = 0
                    if restarts[sysid] > MAX_RESTARTS:
                        raise MissionUploadError(
                            f"fence upload to vehicle {sysid}: {MAX_RESTARTS} uploads without a "
                            f"MISSION_ACK; check the link"
                        )
                    send_count(vehicle)
                else:
                    send_fence_item(vehicle, asked, circles[asked])  # it may not have come
                    last_sent[sysid] = now
                    resends[sysid] += 1
    for sysid, result in done.items():
        if result != mavlink.MAV_MISSION_ACCEPTED:
            raise MissionUploadError(
                f"vehicle {sysid} refused the fence upload: "
                f"{enum_name('MAV_MISSION_RESULT', result or 0)}"
                f" (an autopilot still initialising answers NO_SPACE; wait for STANDBY)"
            )
