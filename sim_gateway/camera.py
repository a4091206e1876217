"""The camera component (MAV_COMP_ID_CAMERA = 100) of a simulated vehicle: sensor looks out,
engagement captures in. The wire mapping is specified in docs/mavlink.md.

A look is reported as CAMERA_IMAGE_CAPTURED, encoded by ``mavlink_wire.looks``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from planner.engagement import EngagementOutcome


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
