"""Lockstep: simulated time advances only as far as the ground station allows.

With ``swarmplan sim --lockstep`` the simulator runs its ticks back to back (as fast as the CPU
goes) but never past a *horizon* the ground station grants, and holds there until it grants the
next one. A ground station that grants one decision period at a time, and sends its commands
(and waits for their ACKs) while the simulator holds, gets the same flight for the same seed
however fast or slow either side runs: every command takes effect at the same simulated instant.

The wire protocol (docs/simulator.md, "Lockstep"):

* grant, ground station -> any vehicle: ``SYSTEM_TIME`` with ``time_unix_usec = 0`` and
  ``time_boot_ms = T``: "you may run until simulated time T" (a horizon never moves back).
  Only the clock master's grants count (:class:`ClockMaster`): they must come from the address
  the vehicle sends its telemetry to, in the system id of the first grant from there.
  ``time_boot_ms = 0xFFFFFFFF`` releases the lock (the simulator then runs at ``--speedup``).
  A real autopilot ignores a SYSTEM_TIME without UTC, so a grant sent to one is harmless; a
  ground station sending its real clock (``time_unix_usec > 0``) is not a grant.
* hold, every vehicle -> ground station: on reaching the horizon each vehicle sends HEARTBEAT
  then GLOBAL_POSITION_INT (``time_boot_ms = T``). On one UDP socket pair datagrams arrive in
  order, so once a vehicle's GLOBAL_POSITION_INT at T has arrived, so has everything it sent
  before (the sensor look taken at T, if T is a decision boundary), and everything it sends
  until the next grant describes it at T.

Simulated time stays at 0 until the first grant. If the ground station that has granted time then
goes silent (no grant and no HEARTBEAT of its own) for ``timeout_wall_s`` wall seconds (it
crashed, its link was cut), the simulator releases the lock itself, so its vehicles' failsafes can
act; a stranger's heartbeats do not hold it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

Address = tuple[str, int]

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
        elif time_boot_ms / 1000.0 == self.horizon_s and self.held_at_s == self.horizon_s:
            # granted again where we hold: the ground station has not heard our hold marker (a
            # datagram lost, or dropped by its full socket after a long computation): again
            self.held_at_s = None

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


#: refusals said in the log, one line per sender (system id, address); later senders only counted
TOLD_SENDERS_MAX = 10


@dataclass
class ClockMaster:
    """Who may drive the clock: the ground station the vehicles are bound to.

    A vehicle sends its telemetry to one fixed address (``--gcs-host``/``--gcs-port``, or its
    ``--per-vehicle-ports`` port), and only that ground station hears it; so a grant counts only
    if it comes *from* that address (to the socket of a vehicle that sends there), and from one
    system id: the one of the first grant from there (``system_id``, bound for the run). The
    address is the operator's configuration, not whoever talks first, so a stranger that sends
    before the daemon binds nothing. A grant from a vehicle's own system id never counts.
    Refused grants are counted (``refused``, the summary's ``foreign_grants``) and said once per
    sender."""

    system_id: int | None = None
    last_heard_wall_s: float | None = None  # the master's newest grant or heartbeat
    refused: int = 0
    told: set[tuple[int, Address | None]] = field(default_factory=set)

    def admits(
        self, sysid: int, sender: Address | None, station: Address | None, vehicle_ids: set[int]
    ) -> bool:
        """Does a grant from ``sysid`` at ``sender``, arriving on the socket of a vehicle that
        sends to ``station``, count? The first one from ``station`` binds its system id."""
        why = self.refusal(sysid, sender, station, vehicle_ids)
        if why is None:
            return True
        self.refused += 1
        key = (sysid, sender)
        if key not in self.told and len(self.told) < TOLD_SENDERS_MAX:
            self.told.add(key)
            print(
                f"sim: refused a lockstep grant from system {sysid} at {show_address(sender)}: "
                f"{why}; only the ground station the vehicles send to drives the clock (further "
                f"grants of this sender are counted in foreign_grants)",
                flush=True,
            )
        return False

    def refusal(
        self, sysid: int, sender: Address | None, station: Address | None, vehicle_ids: set[int]
    ) -> str | None:
        """Why such a grant does not count (None: it does, and binds the system id)."""
        if sysid in vehicle_ids:
            return f"system {sysid} is a simulated vehicle"
        if sender is None or sender != station:
            where = f"{show_address(station)}, where the vehicle sends"
            return f"it comes from {show_address(sender)}, not from {where}"
        if self.system_id is None:
            self.system_id = sysid
        if sysid != self.system_id:
            return f"the clock is bound to system {self.system_id}, the first to grant from there"
        return None

    def is_master(self, sysid: int, sender: Address | None, station: Address | None) -> bool:
        """True for a frame of the bound ground station (its system id, from its address)."""
        return sysid == self.system_id and sender is not None and sender == station


def show_address(address: Address | None) -> str:
    """``host:port`` of an address (None: a frame fed in without a socket)."""
    return "no socket" if address is None else f"{address[0]}:{address[1]}"
