"""Ground-station link failsafe, ArduPlane style (FS_GCS_ENABL, FS_SHORT_*, FS_LONG_*).

A ground station is anything that sends a HEARTBEAT from a system id that is not one of the
simulated vehicles (MAVProxy 255, MAVSDK 245, the planner daemon...). Once one has been heard, a
flying vehicle that hears none for FS_SHORT_TIMEOUT seconds enters the short failsafe (it
circles, unless it is already in AUTO / RTL / LOITER / CIRCLE), and after FS_LONG_TIMEOUT the long
failsafe (RTL). A heartbeat during the short failsafe restores the mode the vehicle was in; the
long failsafe leaves the vehicle in RTL, as on ArduPlane.

The timeouts count wall-clock seconds: a ground station sends heartbeats at a wall-clock rate
(1 Hz), so at a 50x speedup 1 s of link silence is 50 s of simulated flight.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass


class FailsafeEvent(enum.Enum):
    NONE = 0
    SHORT = 1  # enter the short failsafe now
    LONG = 2  # enter the long failsafe now
    CLEARED = 3  # the link came back


@dataclass
class GcsFailsafe:
    """Link state of one vehicle."""

    last_heartbeat_wall_s: float | None = None
    stage: int = 0  # 0 none, 1 short, 2 long
    mode_before: int | None = None

    def heard(self, now_wall_s: float) -> FailsafeEvent:
        """A ground-station heartbeat arrived."""
        self.last_heartbeat_wall_s = now_wall_s
        if self.stage:
            self.stage = 0
            return FailsafeEvent.CLEARED
        return FailsafeEvent.NONE

    def check(
        self, now_wall_s: float, enabled: bool, flying: bool, short_s: float, long_s: float
    ) -> FailsafeEvent:
        """The event due at ``now_wall_s`` (at most one stage per call)."""
        if not enabled or not flying or self.last_heartbeat_wall_s is None:
            return FailsafeEvent.NONE
        silent = now_wall_s - self.last_heartbeat_wall_s
        if self.stage < 2 and silent >= long_s:
            self.stage = 2
            return FailsafeEvent.LONG
        if self.stage < 1 and silent >= short_s:
            self.stage = 1
            return FailsafeEvent.SHORT
        return FailsafeEvent.NONE
