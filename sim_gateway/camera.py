"""The camera component (MAV_COMP_ID_CAMERA = 100) of a simulated vehicle: sensor looks out,
engagement captures in. The wire mapping is specified in docs/mavlink.md.

A look is reported as CAMERA_IMAGE_CAPTURED whose ``file_url`` lists the detected cells as
offsets from the look cell: ``look:dx,dy;dx,dy`` (``look:`` alone when nothing was detected);
a list longer than the 205-character field continues in further messages of the same
``image_index`` whose text starts ``look+:``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

from mavlink_bridge.protocol import mavlink
from mavlink_bridge.vehicle_state import parse_look_offsets
from planner.engagement import EngagementOutcome

FILE_URL_CHARS = 205
LOOK_PREFIX = "look:"
LOOK_CONTINUATION_PREFIX = "look+:"


def look_urls(offsets: Iterable[tuple[int, int]]) -> list[str]:
    """The ``file_url`` texts of one look; each fits in 205 characters."""
    entries = [f"{dx},{dy}" for dx, dy in offsets]
    urls: list[str] = []
    current = LOOK_PREFIX
    used = 0  # entries in the current text
    for entry in entries:
        extra = entry if used == 0 else ";" + entry
        if len(current) + len(extra) > FILE_URL_CHARS:
            urls.append(current)
            current, used, extra = LOOK_CONTINUATION_PREFIX, 0, entry
        current += extra
        used += 1
    urls.append(current)
    return urls


def parse_look_url(url: str) -> list[tuple[int, int]]:
    """Offsets in one ``file_url`` text (the inverse of :func:`look_urls`, for tests and tools),
    read by the daemon's own parser (``mavlink_bridge.vehicle_state.parse_look_offsets``)."""
    for prefix in (LOOK_CONTINUATION_PREFIX, LOOK_PREFIX):
        if url.startswith(prefix):
            return parse_look_offsets(url[len(prefix) :])
    raise ValueError(f"not a look url: {url!r}")


def look_messages(
    offsets: Iterable[tuple[int, int]],
    index: int,
    time_boot_ms: int,
    time_utc_us: int,
    lat_e7: int,
    lon_e7: int,
    alt_amsl_mm: int,
    relative_alt_mm: int,
) -> list[mavlink.MAVLink_camera_image_captured_message]:
    """The CAMERA_IMAGE_CAPTURED messages of one look (docs/mavlink.md, "Sensor looks"): look
    number ``index``, taken at the given position and time, detected cells as ``offsets`` from
    the look cell."""
    return [
        mavlink.MAVLink_camera_image_captured_message(
            time_boot_ms,
            time_utc_us,
            0,
            lat_e7,
            lon_e7,
            alt_amsl_mm,
            relative_alt_mm,
            [1.0, 0.0, 0.0, 0.0],
            index,
            1,
            url.encode(),
        )
        for url in look_urls(offsets)
    ]


def engagement_sequence(p2: float, p3: float, p4: float) -> int | None:
    """The engagement sequence number of a MAV_CMD_IMAGE_START_CAPTURE (p2 = 0 interval, p3 = 1
    image, p4 = an integer >= 0), or None for any other form (answered DENIED)."""
    if p2 != 0 or p3 != 1 or not (math.isfinite(p4) and p4 >= 0 and p4 == int(p4)):
        return None
    return int(p4)


def engagement_text(sequence: int, outcome: EngagementOutcome) -> str:
    """The camera's STATUSTEXT for people, after a new engagement."""
    if outcome.success:
        return f"Engagement {sequence}: target {outcome.target_id} serviced"
    return f"Engagement {sequence}: no target in range"


class EngagementLog:
    """Outcomes by engagement sequence number, so a repeated request replays, never re-engages."""

    def __init__(self) -> None:
        self._by_sequence: dict[int, EngagementOutcome] = {}

    def get(self, sequence: int) -> EngagementOutcome | None:
        return self._by_sequence.get(sequence)

    def record(self, sequence: int, outcome: EngagementOutcome) -> None:
        self._by_sequence[sequence] = outcome

    def resolve(
        self, sequence: int, engage: Callable[[], EngagementOutcome]
    ) -> tuple[EngagementOutcome, bool]:
        """The outcome of request ``sequence`` and whether it is a replay: a new number calls
        ``engage()`` (ground truth) once, a repeated one returns its first outcome."""
        outcome = self._by_sequence.get(sequence)
        if outcome is not None:
            return outcome, True
        outcome = engage()
        self._by_sequence[sequence] = outcome
        return outcome, False

    def __len__(self) -> int:
        return len(self._by_sequence)
