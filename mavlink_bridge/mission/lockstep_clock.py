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

from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from planner.errors import UserError

RELEASE_MS = 0xFFFFFFFF
REGRANT_WALL_S = 0.5  # a grant is resent this often while waiting (a lost datagram never stalls)


class LockstepError(UserError):
    """The simulator did not reach the granted time."""


class LockstepReleasedError(LockstepError):
    """The vehicles' clock runs past the granted time: their simulator does not hold (someone
    else released or granted it time, or it is not in lockstep)."""


def _progress(vehicles: Sequence[VehicleState], target_ms: int) -> int:
    """How far the vehicles still waited for have come towards ``target_ms`` (the sum of their
    clocks, each counted up to it: position or SYSTEM_TIME, whichever is newer)."""
    return sum(min(v.clock_ms, target_ms) for v in vehicles if not v.lost)


class LockstepClock:
    """Grants simulated time to the vehicles and waits until they hold at it."""

    def __init__(self, link: SwarmLink, step_s: float, wall_timeout_s: float = 30.0) -> None:
        self.link = link
        self.step_ms = max(1, round(step_s * 1000))
        self.wall_timeout_s = wall_timeout_s
        self.time_ms = 0  # where the vehicles hold now
        self.grants = 0
        self.holds = 0  # grants of ours every vehicle held at: the simulator was in lockstep

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
        # what the vehicles' clocks may reach (telemetry_plausibility.py); released: anything
        self.link.plausibility.granted_ms = None if until_ms == RELEASE_MS else until_ms
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
        daemon's loss detection marks them lost, and then they are not waited for). The wait
        ends in an error only once the vehicles' clocks have not moved towards the grant for
        ``wall_timeout_s``: a simulator of hundreds of vehicles on a busy machine may take
        longer than that for a decision period (300 vehicles: 31 s for 10 s of simulated time,
        clocks moving all along), and is waited for while it moves."""
        target = (self.time_ms // self.step_ms + 1) * self.step_ms
        self.grant(vehicles, target)
        moved = last_grant = time.monotonic()
        progress = _progress(vehicles, target)
        while True:
            self.link.pump(0.002)
            if on_pump is not None:
                on_pump()
            if all(v.lost or v.time_boot_ms >= target for v in vehicles):
                break
            self._check_held(vehicles, target)
            now = time.monotonic()
            now_progress = _progress(vehicles, target)
            if now_progress > progress:
                progress, moved = now_progress, now
            if now - moved > self.wall_timeout_s:
                behind = [str(v.key) for v in vehicles if not v.lost and v.time_boot_ms < target]
                raise LockstepError(
                    f"vehicle {', '.join(behind)} did not reach simulated time "
                    f"{target / 1000:g} s: no vehicle's clock moved towards it for "
                    f"{self.wall_timeout_s:g} s: its "
                    f"simulator is not running with --lockstep, is stopped, or refuses our grants "
                    f"(a lockstep simulator takes them only from the address its vehicles send "
                    f"to: check its --gcs-host/--gcs-port, and its log for 'refused a lockstep "
                    f"grant')"
                )
            if now - last_grant > REGRANT_WALL_S:
                self.grant(vehicles, target)
                last_grant = now
        self.time_ms = target
        self.holds += 1
        return target

    def _check_held(self, vehicles: Sequence[VehicleState], target: int) -> None:
        """A vehicle whose clock runs past the grant (its positions, dropped, say so): the
        simulator does not hold any more. Decisions would no longer take effect at the instants
        they were made for: stop, in one line that names what can have happened."""
        trust = self.link.plausibility
        free = [v.key for v in vehicles if not v.lost and trust.running_free(v.key)]
        if free:
            raise LockstepReleasedError(
                f"vehicle {', '.join(map(str, free))} ran past the granted simulated time "
                f"{target / 1000:g} s{self._why_free()}"
            )

    def _why_free(self) -> str:
        """What can make a simulator run past our grant, and what to do, most likely first."""
        if self.holds:  # it held at our grants, so it was in lockstep: something released it
            return (
                f" after holding at each of our grants up to {self.time_ms / 1000:g} s: "
                f"something else released or advanced its clock (another ground station or a "
                f"stranger on its link, sending from the address its vehicles send to; turn "
                f"signing on), or its simulator released the lock after this daemon was silent "
                f"for its --lockstep-timeout; no decision is made against a free-running clock: "
                f"find what released it, then restart the simulator with --lockstep"
            )
        return (
            ": something else grants it time (another ground station on its link?) or its "
            "simulator is not in lockstep (started without --lockstep, or released after a "
            "ground station was silent); no decision is made against a free-running clock: "
            "restart the simulator with --lockstep, or run the daemon paced (--time-scale, no "
            "--lockstep)"
        )

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
