"""What the simulated vehicles receive. :class:`Inbox` reads every datagram waiting on their
sockets, parses each on its own (with signing on, refusing what is not signed: the parser's
signature check, ``sim_gateway/signing.py``), handles a frame that reached several vehicle
sockets once, and hands each good message to the vehicle(s) it is addressed to
(``sim_gateway/message_handlers.py``); a lockstep grant goes to the clock instead, if it comes
from the vehicles' ground station (``sim_gateway/lockstep.py``), and a swarm-link TUNNEL frame
to the radio (``sim_gateway/radio.py``).
"""

from __future__ import annotations

import selectors
import struct
import time
from collections.abc import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_gateway.lockstep import Address, ClockMaster, LockstepGate
from sim_gateway.mavlink_endpoint import DatagramParser, LinkStats, VehicleSocket
from sim_gateway.message_handlers import AUTOPILOT_ONLY, HANDLERS
from sim_gateway.radio import is_swarm_frame
from sim_gateway.vehicle import Vehicle

DUPLICATE_WINDOW_S = 2.0
SwarmFrameSink = Callable[[mavlink.MAVLink_message, VehicleSocket | None], None]


class Inbox:
    """The one way in of a fleet of simulated vehicles."""

    def __init__(
        self,
        vehicles: list[Vehicle],
        stats: LinkStats,
        lockstep: LockstepGate,
        clock_master: ClockMaster,
    ) -> None:
        self.vehicles = vehicles
        self.sysids = {v.sysid: v for v in vehicles}
        self.stats = stats
        self.parser = DatagramParser(stats)
        self.lockstep = lockstep
        self.clock_master = clock_master
        #: where a swarm-link TUNNEL frame goes (the simulator's radio): ``(message, sock)``
        self.on_swarm_frame: SwarmFrameSink | None = None
        self.recent_frames: dict[tuple[Address | None, bytes], float] = {}
        self.next_purge_wall = 0.0
        self.selector = selectors.DefaultSelector()
        for vehicle in vehicles:
            self.selector.register(vehicle.sock.sock, selectors.EVENT_READ, vehicle.sock)

    def poll(self, timeout_s: float) -> int:
        """Wait up to ``timeout_s`` for datagrams and handle all that arrived; returns how many."""
        handled = 0
        for key, _ in self.selector.select(timeout_s):
            sock: VehicleSocket = key.data
            for data, sender in sock.receive_all():
                self.handle_datagram(data, sock, sender)
                handled += 1
        return handled

    def handle_datagram(
        self, data: bytes, sock: VehicleSocket | None = None, sender: Address | None = None
    ) -> None:
        """One datagram that arrived on ``sock`` from ``sender`` (None: fed in directly)."""
        now = time.monotonic()
        for message in self.parser.parse(data):
            # a frame one sender wrote to several vehicle sockets is handled once; the same
            # bytes from another sender are its own (a copy sent ahead cannot mask the original)
            key = (sender, bytes(message.get_msgbuf()))
            seen = self.recent_frames.get(key)
            if seen is not None and now - seen < DUPLICATE_WINDOW_S:
                self.stats.duplicates += 1
                continue
            self.recent_frames[key] = now
            self.dispatch(message, sock, sender)
        if now >= self.next_purge_wall:
            self.recent_frames = {
                k: t for k, t in self.recent_frames.items() if now - t < DUPLICATE_WINDOW_S
            }
            self.next_purge_wall = now + DUPLICATE_WINDOW_S

    def dispatch(
        self,
        message: mavlink.MAVLink_message,
        sock: VehicleSocket | None = None,
        sender: Address | None = None,
    ) -> None:
        """Hand a good message to the vehicle(s) it is addressed to; a lockstep grant to the
        clock, if it comes from the vehicles' ground station."""
        mtype = message.get_type()
        stats = self.stats
        stats.by_type[mtype] = stats.by_type.get(mtype, 0) + 1
        if mtype == "SYSTEM_TIME" and message.time_unix_usec == 0:
            self.lockstep_grant(message, sock, sender)
            return
        if self.on_swarm_frame is not None and mtype == "TUNNEL" and is_swarm_frame(message):
            self.on_swarm_frame(message, sock)
            return
        if mtype == "HEARTBEAT" and self.clock_master.is_master(
            message.get_srcSystem(), sender, None if sock is None else sock.station
        ):
            self.clock_master.last_heard_wall_s = time.monotonic()  # keeps the lock (lockstep.py)
        handler = HANDLERS.get(mtype)
        if handler is None or message.get_srcSystem() in self.sysids:
            stats.ignored_messages += 1
            return
        target = getattr(message, "target_system", 0)
        if mtype in AUTOPILOT_ONLY and getattr(message, "target_component", 0) not in (0, 1):
            stats.ignored_messages += 1
            return
        if target == 0:
            targets = self.vehicles
        elif target in self.sysids:
            targets = [self.sysids[target]]
        else:
            stats.ignored_messages += 1
            return
        for vehicle in targets:
            try:
                handler(vehicle, message)
            except (
                ValueError,
                TypeError,
                OverflowError,
                ArithmeticError,
                KeyError,
                IndexError,
                struct.error,
            ):
                # a value no handler expected (NaN where an int goes...): refuse it, keep flying
                stats.rejected_commands += 1

    def lockstep_grant(
        self, message: mavlink.MAVLink_message, sock: VehicleSocket | None, sender: Address | None
    ) -> None:
        """A SYSTEM_TIME without UTC that arrived on ``sock`` from ``sender``: a lockstep grant
        if it comes from the vehicles' ground station (``ClockMaster``), else dropped."""
        if not self.lockstep.enabled:
            return  # not a lockstep simulator: a grant means nothing here
        station = None if sock is None else sock.station
        if self.clock_master.admits(message.get_srcSystem(), sender, station, set(self.sysids)):
            self.clock_master.last_heard_wall_s = now = time.monotonic()
            self.lockstep.on_grant(message.time_boot_ms, now)

    def close(self) -> None:
        self.selector.close()
