"""The camera component (MAV_COMP_ID_CAMERA = 100) of a simulated vehicle: sensor looks out,
engagement captures in. The wire mapping is specified in docs/mavlink.md.

A look is reported as CAMERA_IMAGE_CAPTURED whose ``file_url`` lists the detected cells as
offsets from the look cell: ``look:dx,dy;dx,dy`` (``look:`` alone when nothing was detected);
a list longer than the 205-character field continues in further messages of the same
``image_index`` whose text starts ``look+:``.
"""

from __future__ import annotations

from collections.abc import Iterable

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


class EngagementLog:
    """Outcomes by engagement sequence number, so a repeated request replays, never re-engages."""

    def __init__(self) -> None:
        self._by_sequence: dict[int, EngagementOutcome] = {}

    def get(self, sequence: int) -> EngagementOutcome | None:
        return self._by_sequence.get(sequence)

    def record(self, sequence: int, outcome: EngagementOutcome) -> None:
        self._by_sequence[sequence] = outcome

    def __len__(self) -> int:
        return len(self._by_sequence)
