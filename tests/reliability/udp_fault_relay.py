"""A UDP relay that loses, delays, duplicates and reorders datagrams, for fault injection between
the planner daemon and the simulator on loopback.

Wiring: the simulator runs with ``--per-vehicle-ports BASE`` (vehicle ``i`` sends to
``BASE + i``); the relay binds ``BASE .. BASE + N - 1`` and forwards what vehicle ``i`` sends to
the daemon's port *from its socket ``i``*, so the daemon sees each vehicle at its own address and
its replies come back to socket ``i``, which forwards them to the vehicle. Each direction of each
datagram independently:

* is dropped with probability ``loss``;
* waits ``delay_s`` plus a uniform ``[0, jitter_s]`` (so datagrams overtake each other);
* with probability ``reorder``, waits ``reorder_hold_s`` more (it arrives after later ones);
* with probability ``duplicate``, is sent twice (the copy with its own delay).

All randomness comes from one ``random.Random(seed)``; the timing of the operating system still
varies, so a run is reproducible in its fault rates, not to the datagram.

A :class:`GrantHold` given as ``withhold`` stops a lockstep simulator at a chosen place: it
withholds the daemon's time grants from the first hold at which the vehicle is where the test
wants it, until released, so simulated time stops at that decision instant however late the
test's own process gets to run.
"""

from __future__ import annotations

import heapq
import random
import selectors
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from loopback import bind_port_block
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from planner.geodesy import geodetic_to_local_km
from planner.scenario import Origin

Address = tuple[str, int]


@dataclass(frozen=True)
class FaultProfile:
    loss: float = 0.0
    delay_s: float = 0.0
    jitter_s: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    reorder_hold_s: float = 0.05


@dataclass
class RelayCounters:
    received: int = 0
    forwarded: int = 0
    dropped: int = 0
    duplicated: int = 0
    reordered: int = 0
    withheld: int = 0
    by_direction: dict[str, int] = field(default_factory=lambda: {"up": 0, "down": 0})


class FaultRelay(threading.Thread):
    """Relays N vehicles to one daemon port through a faulty link (see the module docstring)."""

    def __init__(
        self,
        daemon_port: int,
        count: int,
        profile: FaultProfile,
        seed: int,
        withhold: Callable[[bytes, str], bool] | None = None,
    ) -> None:
        super().__init__(daemon=True, name="fault-relay")
        self.withhold = withhold  # (datagram, "up" | "down") -> True: not forwarded
        self.daemon_addr: Address = ("127.0.0.1", daemon_port)
        self.profile = profile
        self.rng = random.Random(seed)
        self.socks = bind_port_block(count)
        for s in self.socks:
            s.setblocking(False)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.base_port = self.socks[0].getsockname()[1]
        self.vehicle_addr: list[Address | None] = [None] * count
        self.counters = RelayCounters()
        self.enabled = threading.Event()  # cleared: a plain relay (no faults)
        self.enabled.set()
        self._queue: list[tuple[float, int, int, bytes, Address]] = []
        self._order = 0
        self._halt = threading.Event()
        self._selector = selectors.DefaultSelector()
        for index, s in enumerate(self.socks):
            self._selector.register(s, selectors.EVENT_READ, index)

    def _schedule(self, index: int, data: bytes, dest: Address, direction: str) -> None:
        p, rng, c = self.profile, self.rng, self.counters
        c.received += 1
        if self.withhold is not None and self.withhold(data, direction):
            c.withheld += 1
            return
        faulty = self.enabled.is_set()
        if faulty and rng.random() < p.loss:
            c.dropped += 1
            return
        copies = 2 if faulty and rng.random() < p.duplicate else 1
        c.duplicated += copies - 1
        now = time.monotonic()
        for _ in range(copies):
            wait = p.delay_s + rng.uniform(0.0, p.jitter_s) if faulty else 0.0
            if faulty and rng.random() < p.reorder:
                wait += p.reorder_hold_s
                c.reordered += 1
            self._order += 1
            heapq.heappush(self._queue, (now + wait, self._order, index, data, dest))
            c.by_direction[direction] += 1

    def _release_due(self) -> None:
        now = time.monotonic()
        while self._queue and self._queue[0][0] <= now:
            _, _, index, data, dest = heapq.heappop(self._queue)
            try:
                self.socks[index].sendto(data, dest)
                self.counters.forwarded += 1
            except OSError:
                pass  # nobody listening (yet / any more): the datagram is lost, as on a radio

    def run(self) -> None:
        while not self._halt.is_set():
            timeout = 0.005
            if self._queue:
                timeout = max(0.0, min(timeout, self._queue[0][0] - time.monotonic()))
            for key, _ in self._selector.select(timeout):
                index: int = key.data
                sock = self.socks[index]
                for _ in range(256):
                    try:
                        data, addr = sock.recvfrom(65535)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:
                        continue  # ICMP port unreachable from an earlier send
                    if addr == self.daemon_addr:
                        target = self.vehicle_addr[index]
                        if target is not None:
                            self._schedule(index, data, target, "down")
                    else:
                        self.vehicle_addr[index] = addr
                        self._schedule(index, data, self.daemon_addr, "up")
            self._release_due()

    def stop(self) -> None:
        self._halt.set()
        self.join(5)
        self._selector.close()
        for s in self.socks:
            s.close()


class MessageWithhold:
    """A ``FaultRelay`` withhold that reads the MAVLink messages of each datagram (one parser a
    direction): the datagram is withheld when :meth:`judge` says so of any of them (every one
    is judged)."""

    def __init__(self) -> None:
        self._parsers = {"up": mavlink.MAVLink(None), "down": mavlink.MAVLink(None)}
        for parser in self._parsers.values():
            parser.robust_parsing = True

    def __call__(self, data: bytes, direction: str) -> bool:
        messages = self._parsers[direction].parse_buffer(data) or []
        return any([self.judge(m, direction) for m in messages])

    def judge(self, message: mavlink.MAVLink_message, direction: str) -> bool:
        raise NotImplementedError


class GrantHold(MessageWithhold):
    """Withholds the daemon's lockstep grants (SYSTEM_TIME without UTC, daemon to vehicle) from
    the first one sent while ``hold_at(x_km, y_km)`` is true of the vehicle's last reported
    position (GLOBAL_POSITION_INT, in the scenario's frame from ``origin``), until
    :meth:`release`. The simulator holds at the decision instant it reached; the daemon re-grants
    meanwhile (every 0.5 s) and its first grant after the release goes through. One vehicle."""

    def __init__(self, origin: Origin, hold_at: Callable[[float, float], bool]) -> None:
        super().__init__()
        self.origin = origin
        self.hold_at = hold_at
        self.holding = threading.Event()
        self.released = False
        self.position_km: tuple[float, float] | None = None

    def judge(self, message: mavlink.MAVLink_message, direction: str) -> bool:
        kind = message.get_type()
        if kind == "GLOBAL_POSITION_INT":
            x, y = geodetic_to_local_km(message.lat / 1e7, message.lon / 1e7, self.origin)
            self.position_km = (float(x[0]), float(y[0]))
            return False
        if kind != "SYSTEM_TIME" or message.time_unix_usec != 0 or self.released:
            return False
        at = self.position_km
        if not self.holding.is_set() and at is not None and self.hold_at(*at):
            self.holding.set()
        return self.holding.is_set()

    def release(self) -> None:
        self.released = True
