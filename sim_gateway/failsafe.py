"""Ground-station link failsafe, as ArduPlane does it (FS_GCS_ENABL, FS_LONG_TIMEOUT, FS_LONG_ACTN).

A ground station is anything that sends a HEARTBEAT from a system id that is not one of the
simulated vehicles (MAVProxy 255, MAVSDK 245, the planner daemon...). ArduPlane's GCS failsafe
has one stage (``Plane::check_long_failsafe``): once a ground station has been heard, a flying
vehicle that hears none for FS_LONG_TIMEOUT seconds takes the **long** failsafe action, chosen by
its mode when the failsafe starts (``Plane::failsafe_long_on_event``):

| mode | FS_LONG_ACTN 0 (Continue) | 1 (RTL) | 2 (Glide) | 4 (Auto) |
|---|---|---|---|---|
| AUTO, GUIDED, LOITER | carry on (GUIDED: circle the last target) | RTL | FBWA | AUTO |
| CIRCLE, TAKEOFF, MANUAL, FBWA, FBWB, CRUISE, STABILIZE | RTL | RTL | FBWA | RTL |
| RTL | nothing | nothing | nothing | nothing |

(3, parachute, and 5, AUTOLAND, are RTL here: the simulator has neither.) FS_SHORT_ACTN and
FS_SHORT_TIMEOUT act on a lost RC link only; the simulated planes have no RC, so they are
served as parameters and never act. When heartbeats come back the failsafe ends and the mode
stays what the failsafe made it, as on ArduPlane. FS_GCS_ENABL: 0 off, 1 heartbeat, 2 heartbeat
(and RADIO_STATUS remote RSSI on ArduPlane; heartbeat only here), 3 heartbeat in AUTO only.

The timeout counts wall-clock seconds (ArduPlane counts its own clock): a ground station sends
heartbeats at a wall-clock rate (1 Hz), so at a 50x speedup 1 s of silence is 50 s of flight.
In lockstep (``--lockstep``) the ground station is the clock: no simulated time passes while it
computes (ArduPlane in lockstep SITL counts its own stopped clock), so its silence counts only
once the lock is released (by the ground station, or after ``--lockstep-timeout`` wall seconds
without it); then a silence already longer than FS_LONG_TIMEOUT acts at once. Counting wall
seconds under the lock made a loaded machine's slow decision step a "failsafe" that changed
nothing in the flight but the mode group its ground truth was counted under.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from sim_gateway import flight_modes as modes

GCS_FS_OFF, GCS_FS_HEARTBEAT, GCS_FS_HB_RSSI, GCS_FS_HB_AUTO = 0, 1, 2, 3
LONG_CONTINUE, LONG_RTL, LONG_GLIDE, LONG_PARACHUTE, LONG_AUTO, LONG_AUTOLAND = range(6)
#: modes whose long failsafe honours FS_LONG_ACTN 0 (continue) and 4 (AUTO)
AUTO_MODES = frozenset({modes.AUTO, modes.GUIDED, modes.LOITER})


class FailsafeEvent(enum.Enum):
    NONE = 0
    LONG = 2  # enter the (long) GCS failsafe now
    CLEARED = 3  # the link came back


@dataclass
class GcsFailsafe:
    """Link state of one vehicle."""

    last_heartbeat_wall_s: float | None = None
    stage: int = 0  # 0 none, 2 long (ArduPlane's FAILSAFE_GCS)

    def heard(self, now_wall_s: float) -> FailsafeEvent:
        """A ground-station heartbeat arrived."""
        self.last_heartbeat_wall_s = now_wall_s
        if self.stage:
            self.stage = 0
            return FailsafeEvent.CLEARED
        return FailsafeEvent.NONE

    def check(
        self, now_wall_s: float, enabled: int, flying: bool, mode: int, long_s: float
    ) -> FailsafeEvent:
        """The event due at ``now_wall_s`` for FS_GCS_ENABL ``enabled`` in ``mode``."""
        if not enabled or not flying or self.last_heartbeat_wall_s is None or self.stage:
            return FailsafeEvent.NONE
        if enabled == GCS_FS_HB_AUTO and mode != modes.AUTO:
            return FailsafeEvent.NONE
        if now_wall_s - self.last_heartbeat_wall_s > long_s:
            self.stage = 2
            return FailsafeEvent.LONG
        return FailsafeEvent.NONE


def long_failsafe_mode(mode: int, action: int) -> int | None:
    """The mode ArduPlane switches to on a long failsafe in ``mode`` with FS_LONG_ACTN
    ``action``; None: no change."""
    if mode == modes.RTL:
        return None
    if action == LONG_GLIDE:
        return modes.FBWA
    if mode in AUTO_MODES:
        if action == LONG_CONTINUE:
            return None
        if action == LONG_AUTO:
            return None if mode == modes.AUTO else modes.AUTO
        return modes.RTL
    return modes.RTL
