"""Lockstep: simulated time advances only as far as the ground station allows.

With ``swarmplan sim --lockstep`` the simulator runs its ticks back to back (as fast as the CPU
goes) but never past a *horizon* the ground station grants, and holds there until it grants the
next one. A ground station that grants one decision period at a time, and sends its commands
(and waits for their ACKs) while the simulator holds, gets the same flight for the same seed
however fast or slow either side runs: every command takes effect at the same simulated instant.

The wire protocol (docs/simulator.md, "Lockstep"):

* grant, ground station -> any vehicle: ``SYSTEM_TIME`` with ``time_unix_usec = 0`` and
  ``time_boot_ms = T``: "you may run until simulated time T" (a horizon never moves back).
  ``time_boot_ms = 0xFFFFFFFF`` releases the lock (the simulator then runs at ``--speedup``).
  A real autopilot ignores a SYSTEM_TIME without UTC, so a grant sent to one is harmless; a
  ground station sending its real clock (``time_unix_usec > 0``) is not a grant.
* hold, every vehicle -> ground station: on reaching the horizon each vehicle sends HEARTBEAT
  then GLOBAL_POSITION_INT (``time_boot_ms = T``). On one UDP socket pair datagrams arrive in
  order, so once a vehicle's GLOBAL_POSITION_INT at T has arrived, so has everything it sent
  before (the sensor look taken at T, if T is a decision boundary), and everything it sends
  until the next grant describes it at T.

Simulated time stays at 0 until the first grant. If a ground station that has granted time then
goes silent (no grant and no HEARTBEAT) for ``timeout_wall_s`` wall seconds (it crashed, its link
was cut), the simulator releases the lock itself, so its vehicles' failsafes can act.
"""

from __future__ import annotations

from dataclasses import dataclass

RELEASE_MS = 0xFFFFFFFF  # time_boot_ms of a grant that ends lockstep


@dataclass
class LockstepGate:
    """The horizon simulated time may not pass, and how it was granted."""

    enabled: bool
    timeout_wall_s: float = 10.0
    horizon_s: float = 0.0
    released: bool = False
    grants: int = 0
    last_grant_wall_s: float | None = None
    held_at_s: float | None = None  # the horizon the hold marker was last sent for

    @property
    def locked(self) -> bool:
        """True while ticks need a grant."""
        return self.enabled and not self.released

    def on_grant(self, time_boot_ms: int, now_wall_s: float) -> None:
        """A SYSTEM_TIME grant (already known to come from a ground station, without UTC)."""
        if not self.locked:
            return
        self.last_grant_wall_s = now_wall_s
        if time_boot_ms >= RELEASE_MS:
            self.released = True
            return
        if time_boot_ms / 1000.0 > self.horizon_s:
            self.grants += 1  # horizons granted (a repeated or older grant only keeps it alive)
            self.horizon_s = time_boot_ms / 1000.0

    def allows(self, next_time_s: float) -> bool:
        """May the simulator tick to ``next_time_s``?"""
        return not self.locked or next_time_s <= self.horizon_s + 1e-9

    def timed_out(self, now_wall_s: float, gcs_heard_wall_s: float | None) -> bool:
        """Release the lock when the ground station that granted time has gone quiet (neither a
        grant nor a heartbeat, ``gcs_heard_wall_s``, for ``timeout_wall_s``)."""
        if not self.locked or self.last_grant_wall_s is None:
            return False
        heard = max(self.last_grant_wall_s, gcs_heard_wall_s or 0.0)
        if now_wall_s - heard > self.timeout_wall_s:
            self.released = True
            return True
        return False
