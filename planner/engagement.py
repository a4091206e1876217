"""Target confirmation and engagement (section 3.2.1): a target counts as confirmed when the
existence probability of a cell in a UAV's own map reaches the confirmation threshold; the UAV
then flies to it under the attraction force until it is within the engage radius and asks for
an engagement (confirming / servicing the target; never a weapon). When several targets are
confirmed the one of higher expected value comes first."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EngagementOutcome:
    """What an engagement request at a UAV position came back with."""

    success: bool
    target_id: int = 0  # 0 when no target was within the engage radius
    value: float = 0.0
