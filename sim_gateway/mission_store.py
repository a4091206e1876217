"""Stored missions, fences and rally points of one vehicle, and the state of a transfer.

A :class:`MissionItem` is the content of a MISSION_ITEM_INT (lat / lon as degE7 integers).
:class:`MissionStore` keeps one list per mission type (0 mission, 1 fence, 2 rally) and validates
uploads the way ArduPilot does (supported commands, frames and coordinates);
:class:`UploadTransfer` is the vehicle's side of one upload in progress. The MAVLink messages
themselves are built and parsed by ``sim_gateway.mission_protocol``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink

MISSION, FENCE, RALLY = (
    mavlink.MAV_MISSION_TYPE_MISSION,
    mavlink.MAV_MISSION_TYPE_FENCE,
    mavlink.MAV_MISSION_TYPE_RALLY,
)
MISSION_TYPES = (MISSION, FENCE, RALLY)
MAX_ITEMS = 700  # per mission type (ArduPlane on SITL stores hundreds)

#: Navigation and DO commands an uploaded mission may contain (others: MAV_MISSION_UNSUPPORTED).
MISSION_COMMANDS = frozenset(
    {
        mavlink.MAV_CMD_NAV_WAYPOINT,
        mavlink.MAV_CMD_NAV_LOITER_UNLIM,
        mavlink.MAV_CMD_NAV_LOITER_TURNS,
        mavlink.MAV_CMD_NAV_LOITER_TIME,
        mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH,
        mavlink.MAV_CMD_NAV_LAND,
        mavlink.MAV_CMD_NAV_TAKEOFF,
        mavlink.MAV_CMD_DO_CHANGE_SPEED,
        mavlink.MAV_CMD_DO_JUMP,
        mavlink.MAV_CMD_DO_SET_HOME,
        mavlink.MAV_CMD_DO_DIGICAM_CONTROL,
        mavlink.MAV_CMD_IMAGE_START_CAPTURE,
        mavlink.MAV_CMD_DO_SET_CAM_TRIGG_DIST,
    }
)
FENCE_COMMANDS = frozenset(
    {
        mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
        mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
        mavlink.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
        mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION,
        mavlink.MAV_CMD_NAV_FENCE_RETURN_POINT,
    }
)
RALLY_COMMANDS = frozenset({mavlink.MAV_CMD_NAV_RALLY_POINT})
COMMANDS_BY_TYPE = {MISSION: MISSION_COMMANDS, FENCE: FENCE_COMMANDS, RALLY: RALLY_COMMANDS}
GLOBAL_FRAMES = frozenset(
    {
        mavlink.MAV_FRAME_GLOBAL,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
        mavlink.MAV_FRAME_GLOBAL_INT,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    }
)
FRAMES = GLOBAL_FRAMES | {mavlink.MAV_FRAME_MISSION}
#: Frames whose altitude is above home (the others of GLOBAL_FRAMES are above mean sea level).
RELATIVE_FRAMES = (mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)


@dataclass(frozen=True)
class MissionItem:
    """One stored item; ``x`` / ``y`` are latitude / longitude in degE7, ``z`` altitude in m."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int = MISSION

    @property
    def lat_deg(self) -> float:
        return self.x / 1e7

    @property
    def lon_deg(self) -> float:
        return self.y / 1e7

    def is_relative_alt(self) -> bool:
        return self.frame in RELATIVE_FRAMES


def validate_item(item: MissionItem) -> int:
    """MAV_MISSION_ACCEPTED, or the MAV_MISSION_* error a real autopilot would answer."""
    if item.command not in COMMANDS_BY_TYPE[item.mission_type]:
        return mavlink.MAV_MISSION_UNSUPPORTED
    if item.frame not in FRAMES:
        return mavlink.MAV_MISSION_UNSUPPORTED_FRAME
    for k, value in enumerate((item.param1, item.param2, item.param3, item.param4)):
        if math.isinf(value):
            return mavlink.MAV_MISSION_INVALID_PARAM1 + k
    if not math.isfinite(item.z):
        return mavlink.MAV_MISSION_INVALID_PARAM7
    if item.frame in GLOBAL_FRAMES:
        if not -90e7 <= item.x <= 90e7:
            return mavlink.MAV_MISSION_INVALID_PARAM5_X
        if not -180e7 <= item.y <= 180e7:
            return mavlink.MAV_MISSION_INVALID_PARAM6_Y
    if item.command == mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION and not item.param1 > 0:
        return mavlink.MAV_MISSION_INVALID_PARAM1
    return mavlink.MAV_MISSION_ACCEPTED


@dataclass
class UploadTransfer:
    """An upload (GCS -> vehicle) in progress: who sends it, how many items, which are in."""

    mission_type: int
    count: int
    peer: tuple[int, int]  # (sysid, compid) of the uploader
    items: list[MissionItem] = field(default_factory=list)
    use_request_int: bool = False  # switched on when the uploader NAKs the legacy MISSION_REQUEST
    last_request_wall_s: float = 0.0
    retries: int = 0

    @property
    def next_seq(self) -> int:
        return len(self.items)

    @property
    def complete(self) -> bool:
        return len(self.items) == self.count


class MissionStore:
    """The three item lists of one vehicle and the index of the current mission item."""

    def __init__(self) -> None:
        self.items: dict[int, list[MissionItem]] = {t: [] for t in MISSION_TYPES}
        self.current_seq = 0
        self.upload: UploadTransfer | None = None

    def count(self, mission_type: int) -> int:
        return len(self.items[mission_type])

    def replace(self, mission_type: int, items: list[MissionItem]) -> None:
        self.items[mission_type] = list(items)
        if mission_type == MISSION:
            self.current_seq = 1 if len(items) > 1 else 0

    def mission(self) -> list[MissionItem]:
        return self.items[MISSION]
