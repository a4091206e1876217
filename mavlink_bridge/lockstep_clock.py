"""The daemon's side of lockstep: grant simulated time one decision period at a time.

Against ``swarmplan sim --lockstep`` the daemon is the clock master: the simulator holds at the
horizon the daemon grants and tells it so (HEARTBEAT, then GLOBAL_POSITION_INT stamped with the
held time, after the sensor looks of that instant). The daemon sends its commands and collects
their ACKs while the simulator holds, then grants the next decision period. Every command thus
takes effect at the same simulated instant on every run, which makes a run with a given seed
repeatable, and the pace is whatever both sides can do (see docs/simulator.md, "Lockstep").

Grant: SYSTEM_TIME with time_unix_usec = 0 and time_boot_ms = the horizon; 0xFFFFFFFF releases
the lock. A real autopilot ignores a SYSTEM_TIME without UTC, so the daemon never harms one by
granting, but it only grants when told the vehicles are a lockstep simulator (``--lockstep``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from mavlink_bridge.swarm_link import SwarmLink
from mavlink_bridge.vehicle_state import VehicleState
from planner.errors import UserError

RELEASE_MS = 0xFFFFFFFF
REGRANT_WALL_S = 0.5  # a grant is resent this often while waiting (a lost datagram never stalls)


class LockstepError(UserError):
    """The simulator did not reach the granted time."""


class LockstepClock:
    """Grants simulated time to the vehicles and waits until they hold at it."""

    def __init__(self, link: SwarmLink, step_s: float, wall_timeout_s: float = 30.0) -> None:
        self.link = link
        self.step_ms = max(1, round(step_s * 1000))
        self.wall_timeout_s = wall_timeout_s
        self.time_ms = 0  # where the vehicles hold now
        self.grants = 0

    def sync(self, vehicles: Sequence[VehicleState]) -> None:
        """Take the vehicles' newest time as the current one (the simulator starts held at 0)."""
        times = [v.time_boot_ms for v in vehicles if v.has_position]
        self.time_ms = max([self.time_ms, *times])

    def grant(self, vehicles: Sequence[VehicleState], until_ms: int) -> None:
        """SYSTEM_TIME(time_unix_usec=0, time_boot_ms=until_ms) to every vehicle still heard.

        ``until_ms`` comes from the vehicles' own clocks (``sync``): a horizon a uint32 cannot
        hold, or one that would read as the release, is refused with one line, never packed."""
        if until_ms != RELEASE_MS and not 0 <= until_ms < RELEASE_MS:
            raise LockstepError(
                f"cannot grant simulated time {until_ms / 1000:g} s: beyond what SYSTEM_TIME "
                f"holds (49.7 days); restart the simulator (its clock is where it should not be)"
            )
        if until_ms != RELEASE_MS:
            self.link.plausibility.granted_ms = until_ms
        for v in vehicles:
            if not v.lost:
                v.link.mav.system_time_send(0, until_ms)
        self.grants += 1

    def advance(
        self,
        vehicles: Sequence[VehicleState],
        on_pump: Callable[[], None] | None = None,
    ) -> int:
        """Grant up to the next decision boundary and wait until every vehicle still heard holds
        there. Returns the new time (ms). Vehicles that fall silent are left to ``on_pump`` (the
        daemon's loss detection marks them lost, and then they are not waited for)."""
        target = (self.time_ms // self.step_ms + 1) * self.step_ms
        self.grant(vehicles, target)
        started = last_grant = time.monotonic()
        while True:
            self.link.pump(0.002)
            if on_pump is not None:
                on_pump()
            if all(v.lost or v.time_boot_ms >= target for v in vehicles):
                break
            now = time.monotonic()
            if now - started > self.wall_timeout_s:
                behind = [
                    str(v.system_id) for v in vehicles if not v.lost and v.time_boot_ms < target
                ]
                raise LockstepError(
                    f"vehicle {', '.join(behind)} did not reach simulated time {target / 1000:g} s "
                    f"within {self.wall_timeout_s:g} s of the grant; is the simulator running "
                    f"with --lockstep?"
                )
            if now - last_grant > REGRANT_WALL_S:
                self.grant(vehicles, target)
                last_grant = now
        self.time_ms = target
        return target

    def run_until(
        self,
        done: Callable[[], bool],
        vehicles: Sequence[VehicleState],
        max_sim_s: float,
        on_pump: Callable[[], None] | None = None,
    ) -> bool:
        """Advance one decision period at a time until ``done()`` (True) or ``max_sim_s`` of
        simulated time have passed (False)."""
        self.sync(vehicles)
        start = self.time_ms
        self.link.pump(0.0)
        while not done():
            if self.time_ms - start >= max_sim_s * 1000:
                return False
            self.advance(vehicles, on_pump)
        return True

    def release(self, vehicles: Sequence[VehicleState]) -> None:
        """Let the simulator run freely again (sent twice: it is a single datagram each)."""
        for _ in range(2):
            self.grant(vehicles, RELEASE_MS)
