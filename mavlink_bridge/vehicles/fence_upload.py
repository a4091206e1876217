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

from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_wire.protocol import AUTOPILOT_COMPONENT_ID, enum_name, mavlink
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


#: a refused upload is started again (every retry interval) for this long after the first
#: refusal before the refusal stands: PX4 SITL answered MAV_MISSION_ERROR to an upload made
#: just after its boot, while its mission storage was still starting (for more than 10 s with
#: three instances at 5x on a loaded 2-core machine)
REFUSED_RETRY_S = 30.0


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
    transfers = [_FenceTransfer(vehicle, circles) for vehicle in vehicles]
    for transfer in transfers:
        transfer.send_count()
        transfer.heard = time.monotonic()
    while any(transfer.result is None for transfer in transfers):
        link.pump(0.01)
        now = time.monotonic()
        for transfer in transfers:
            if transfer.result is None:
                transfer.step(now, stall_timeout_s, retry_interval_s)
    for transfer in transfers:
        if transfer.result != mavlink.MAV_MISSION_ACCEPTED:
            raise MissionUploadError(
                f"vehicle {transfer.vehicle.key} refused the fence upload: "
                f"{enum_name('MAV_MISSION_RESULT', transfer.result or 0)}"
                f" for {REFUSED_RETRY_S:g} s (an autopilot still initialising answers NO_SPACE or"
                f" MAV_MISSION_ERROR; wait for STANDBY)"
            )


@dataclass
class _FenceTransfer:
    """One vehicle's side of a fence upload (``upload_fence``): what it asked for last, when
    the daemon last sent and last heard of it, and how often it restarted and resent."""

    vehicle: VehicleState
    circles: list[FenceCircle]
    result: int | None = None  # the MAV_MISSION_RESULT of its MISSION_ACK, once it came
    last_asked: int | None = None  # the item the vehicle asked for last (this upload)
    last_sent: float = 0.0
    heard: float = 0.0  # the vehicle's last message of this upload
    restarts: int = 0
    resends: int = 0  # the last asked item sent again with no answer since
    refused_at: float | None = None  # its first refusal (``REFUSED_RETRY_S``)

    def send_count(self) -> None:
        """Start (again) from MISSION_COUNT, forgetting what the vehicle asked before."""
        vehicle = self.vehicle
        vehicle.mission_requests.clear()
        vehicle.mission_ack = None
        vehicle.link.mav.mission_count_send(
            vehicle.system_id, AUTOPILOT_COMPONENT_ID, len(self.circles),
            mavlink.MAV_MISSION_TYPE_FENCE,
        )  # fmt: skip
        self.last_asked = None
        self.last_sent = time.monotonic()

    def step(self, now: float, stall_timeout_s: float, retry_interval_s: float) -> None:
        """Answer what the vehicle asked for, take its MISSION_ACK, give up when it has said
        nothing for ``stall_timeout_s``, and resend after ``retry_interval_s`` unanswered."""
        self.answer_requests(now)
        ack = self.vehicle.mission_ack
        if ack is not None and ack[1] == mavlink.MAV_MISSION_TYPE_FENCE:
            if ack[0] != mavlink.MAV_MISSION_ACCEPTED and self.refused_at is None:
                self.refused_at = now
            if ack[0] == mavlink.MAV_MISSION_ACCEPTED or now - self.refused_at > REFUSED_RETRY_S:
                self.result = ack[0]
            elif now - self.last_sent > retry_interval_s:
                self.heard = now  # a refusal is an answer: upload again
                self.send_count()
            return
        if now - self.heard > stall_timeout_s:
            raise MissionUploadError(
                f"fence upload to vehicle {self.vehicle.key} stalled: nothing of it heard "
                f"for {stall_timeout_s:g} s; check the link (and that the autopilot supports "
                f"MISSION_TYPE_FENCE)"
            )
        if now - self.last_sent > retry_interval_s:
            self.resend(now)

    def answer_requests(self, now: float) -> None:
        """Send each fence item the vehicle asked for (of this upload, within range), once for
        the requests that came together: a PX4 SITL instance at 5x on a loaded machine asked
        18 times for item 0 within 30 ms (its retry timer runs on its own fast clock), and 18
        answers kept its busy mission storage busier (it refused with MAV_MISSION_ERROR)."""
        n = len(self.circles)
        asked: list[int] = []
        while self.vehicle.mission_requests:
            seq, mission_type = self.vehicle.mission_requests.popleft()
            fence = mission_type == mavlink.MAV_MISSION_TYPE_FENCE
            if fence and 0 <= seq < n and seq not in asked:
                asked.append(seq)
        for seq in asked:
            send_fence_item(self.vehicle, seq, self.circles[seq])
            self.last_asked, self.last_sent, self.heard = seq, now, now
            self.resends = 0

    def resend(self, now: float) -> None:
        """Send again what the vehicle went without: the item it asked for last, up to
        ``ITEM_RESENDS`` times; the MISSION_COUNT when it has not started, its MISSION_ACK was
        lost or its transfer is over (counted as a restart, ``MAX_RESTARTS`` at most)."""
        asked = self.last_asked
        if asked is None or asked == len(self.circles) - 1 or self.resends >= ITEM_RESENDS:
            # not started, its MISSION_ACK lost, or its transfer over: from the start
            self.restarts += asked is not None
            self.resends = 0
            if self.restarts > MAX_RESTARTS:
                raise MissionUploadError(
                    f"fence upload to vehicle {self.vehicle.key}: {MAX_RESTARTS} uploads "
                    f"without a MISSION_ACK; check the link"
                )
            self.send_count()
        else:
            send_fence_item(self.vehicle, asked, self.circles[asked])  # it may not have come
            self.last_sent = now
            self.resends += 1
