"""Transport endpoints of the daemon and the per-vehicle link that sends on them.

Three kinds of endpoint, named the way MAVProxy and pymavlink name them:

* ``udpin:HOST:PORT``: a UDP port the daemon listens on, shared by any number of vehicles (each
  simulator vehicle or ArduPilot SITL sends to it). Vehicles are told apart by system id; the
  address each one sends from is remembered per vehicle, so replies go to the right socket.
* ``udpout:HOST:PORT``: a UDP peer the daemon sends to first (e.g. PX4 SITL's offboard port
  14540 + i); the daemon's heartbeat opens the conversation.
* ``tcp:HOST:PORT``: a TCP server to connect to (ArduPilot SITL instance i: 5760 + 10 i). A
  connection that closes or fails is not an error of the mission: the endpoint notes why
  (``closed_reason``; the vehicles on it are then lost) and connects again with backoff
  (0.5 s, doubling up to 8 s) until the vehicle is back.

A UDP datagram is parsed on its own with a fresh parser, so a corrupt datagram can never swallow
the frames of the next one; frames that parse as ``UNKNOWN_<id>`` (not CRC-checkable) and
``BAD_DATA`` are dropped and counted.
"""

from __future__ import annotations

import contextlib
import errno
import socket
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from mavlink_wire.protocol import GCS_COMPONENT_ID, GCS_SYSTEM_ID, mavlink
from mavlink_wire.tlog import TlogWriter
from planner.errors import UserError

Address = tuple[str, int]

#: Largest number of datagrams read from one socket in one pass, so one busy socket cannot
#: starve the others.
MAX_DATAGRAMS_PER_PASS = 2000
#: TCP reconnect: first wait after a connection closed, and the longest (doubling in between)
RECONNECT_FIRST_S = 0.5
RECONNECT_MAX_S = 8.0
#: a reconnect attempt waits at most this long for the server (the loop must not stall)
RECONNECT_TIMEOUT_S = 0.3


class EndpointError(UserError):
    """An endpoint cannot be opened (bad form, port in use, nothing listening)."""


@dataclass
class LinkStats:
    """Counters of what one endpoint received."""

    datagrams: int = 0
    frames: int = 0
    bad_frames: int = 0
    unknown_frames: int = 0


def _fresh_parser() -> mavlink.MAVLink:
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True  # junk comes back as BAD_DATA instead of raising
    return parser


def _keep(msg: mavlink.MAVLink_message, stats: LinkStats) -> bool:
    kind = msg.get_type()
    if kind == "BAD_DATA":
        stats.bad_frames += 1
        return False
    if kind.startswith("UNKNOWN_"):
        stats.unknown_frames += 1
        return False
    stats.frames += 1
    return True


@dataclass
class Endpoint(ABC):
    """One socket the daemon talks to vehicles through."""

    spec: str
    host: str
    port: int
    stats: LinkStats = field(default_factory=LinkStats)
    #: with MAVLink signing on (mavlink_wire/signing.py): frames it refuses are dropped
    signature_check: Any = None
    sock: socket.socket | None = None  # set by open()
    #: why the connection is down (a TCP peer that went away), None while it works
    closed_reason: str | None = None

    def admits(self, msg: mavlink.MAVLink_message) -> bool:
        """False for a frame the signature check refuses (unsigned, forged or replayed)."""
        return self.signature_check is None or self.signature_check.accept_message(msg)

    def kept(self, parser: mavlink.MAVLink, data: bytes) -> list[mavlink.MAVLink_message]:
        """The frames of ``data`` (one datagram or stream chunk) that ``parser`` makes of it,
        counted, without BAD_DATA, UNKNOWN_<id> and frames the signature check refuses."""
        self.stats.datagrams += 1
        frames = parser.parse_buffer(data) or ()
        return [m for m in frames if _keep(m, self.stats) and self.admits(m)]

    @abstractmethod
    def open(self) -> Endpoint:
        """Open the socket (sets ``sock``); raises EndpointError with a one-line message."""

    def fileno(self) -> int:
        assert self.sock is not None
        return self.sock.fileno()

    @abstractmethod
    def receive(self) -> list[tuple[mavlink.MAVLink_message, Address | None]]:
        """Every frame waiting on the socket now (non-blocking), with the address it came from."""

    @abstractmethod
    def send_to(self, frame: bytes, address: Address | None) -> None:
        """Send one frame to a vehicle at ``address`` (ignored by connected endpoints)."""

    @property
    def needs_first_word(self) -> bool:
        """True if the vehicle waits to hear from us before it talks (udpout)."""
        return False

    def default_address(self) -> Address | None:
        return None

    def reconnect(self, now: float) -> bool:
        """Try to open a closed connection again (when due); True if it is open now."""
        return False

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None


@dataclass
class UdpInEndpoint(Endpoint):
    """A UDP port the daemon listens on; any number of vehicles send to it."""

    def open(self) -> UdpInEndpoint:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, self.port))
        except OSError as exc:
            sock.close()
            if exc.errno == errno.EADDRINUSE:
                raise EndpointError(
                    f"UDP port {self.port} is already in use ({self.spec}): another ground station "
                    f"or daemon listens there; stop it or give another --connect udpin:HOST:PORT"
                ) from None
            raise EndpointError(f"cannot listen on {self.spec}: {exc.strerror}") from None
        sock.setblocking(False)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.sock = sock
        self.port = sock.getsockname()[1]  # the real port when 0 was asked for
        return self

    def parse_datagram(self, data: bytes) -> list[mavlink.MAVLink_message]:
        """The frames kept of one datagram, parsed on its own (a fresh parser)."""
        return self.kept(_fresh_parser(), data)

    def receive(self) -> list[tuple[mavlink.MAVLink_message, Address | None]]:
        out: list[tuple[mavlink.MAVLink_message, Address | None]] = []
        assert self.sock is not None
        for _ in range(MAX_DATAGRAMS_PER_PASS):
            try:
                data, address = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionRefusedError:
                continue  # an ICMP error from an earlier send to a vehicle that went away
            except OSError:
                break  # a socket error is a lost datagram, never the end of the mission
            out += [(msg, address) for msg in self.parse_datagram(data)]
        return out

    def send_to(self, frame: bytes, address: Address | None) -> None:
        if address is None or self.sock is None:
            return
        # UDP: a lost datagram is what retries are for
        with contextlib.suppress(OSError):
            self.sock.sendto(frame, address)


@dataclass
class UdpOutEndpoint(UdpInEndpoint):
    """A UDP peer the daemon speaks to first (it answers to our source address)."""

    def open(self) -> UdpOutEndpoint:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("0.0.0.0", 0))
        sock.setblocking(False)
        self.sock = sock
        return self

    @property
    def needs_first_word(self) -> bool:
        return True

    def default_address(self) -> Address | None:
        return (self.host, self.port)

    def send_to(self, frame: bytes, address: Address | None) -> None:
        super().send_to(frame, address or self.default_address())


@dataclass
class TcpEndpoint(Endpoint):
    """A TCP server (ArduPilot SITL) the daemon connects to; one byte stream, one parser. A
    connection that closes is noted (``closed_reason``) and opened again with backoff."""

    parser: mavlink.MAVLink = field(default_factory=_fresh_parser)
    connect_timeout_s: float = 5.0
    retry_at: float = 0.0  # monotonic instant of the next reconnect attempt
    backoff_s: float = RECONNECT_FIRST_S
    reconnects: int = 0

    def _connect(self, timeout_s: float) -> socket.socket:
        sock = socket.create_connection((self.host, self.port), timeout=timeout_s)
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return sock

    def open(self) -> TcpEndpoint:
        try:
            self.sock = self._connect(self.connect_timeout_s)
        except ConnectionRefusedError:
            raise EndpointError(
                f"nothing listens on {self.spec} (connection refused); start the vehicle or SITL "
                f"first, or check the address"
            ) from None
        except TimeoutError:
            raise EndpointError(
                f"{self.spec} is unreachable (no answer in {self.connect_timeout_s:g} s); "
                f"check the address and the network"
            ) from None
        except OSError as exc:
            raise EndpointError(f"cannot connect to {self.spec}: {exc.strerror or exc}") from None
        return self

    def went_away(self, why: str) -> None:
        """The connection is gone: close it, note why, and plan the first reconnect."""
        if self.sock is not None:
            with contextlib.suppress(OSError):
                self.sock.close()
            self.sock = None
        if self.closed_reason is None:
            self.closed_reason = why
            self.backoff_s = RECONNECT_FIRST_S
            self.retry_at = time.monotonic() + self.backoff_s

    def reconnect(self, now: float) -> bool:
        if self.sock is not None:
            return True
        if now < self.retry_at:
            return False
        try:
            self.sock = self._connect(RECONNECT_TIMEOUT_S)
        except OSError:
            self.backoff_s = min(2 * self.backoff_s, RECONNECT_MAX_S)
            self.retry_at = time.monotonic() + self.backoff_s
            return False
        self.parser = _fresh_parser()  # a new stream: no half frame of the old one
        self.closed_reason = None
        self.reconnects += 1
        return True

    def receive(self) -> list[tuple[mavlink.MAVLink_message, Address | None]]:
        out: list[tuple[mavlink.MAVLink_message, Address | None]] = []
        while self.sock is not None:
            try:
                data = self.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                self.went_away(f"connection failed ({exc.strerror or exc})")
                break
            if not data:
                self.went_away("connection closed by the vehicle")
                break
            out += [(msg, None) for msg in self.kept(self.parser, data)]
        return out

    def send_to(self, frame: bytes, address: Address | None) -> None:
        if self.sock is None:
            return
        try:
            self.sock.sendall(frame)
        except BlockingIOError:
            pass
        except OSError as exc:
            self.went_away(f"send failed ({exc.strerror or exc})")


def parse_endpoint(spec: str) -> Endpoint:
    """An (unopened) endpoint: ``udpin:HOST:PORT``, ``udpout:HOST:PORT`` or ``tcp:HOST:PORT``."""
    parts = spec.split(":")
    kinds = {
        "udpin": UdpInEndpoint,
        "udp": UdpInEndpoint,
        "udpout": UdpOutEndpoint,
        "tcp": TcpEndpoint,
    }
    if len(parts) != 3 or parts[0] not in kinds:
        raise EndpointError(
            f"--connect {spec!r} is not an endpoint; use udpin:HOST:PORT, udpout:HOST:PORT or "
            f"tcp:HOST:PORT (e.g. udpin:0.0.0.0:14550, tcp:127.0.0.1:5760)"
        )
    try:
        port = int(parts[2])
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise EndpointError(f"--connect {spec!r}: port {parts[2]!r} must be a number 0..65535")
    return kinds[parts[0]](spec=spec, host=parts[1] or "0.0.0.0", port=port)


def open_endpoint(spec: str) -> Endpoint:
    """Parse and open an endpoint; raises EndpointError with a one-line message."""
    endpoint = parse_endpoint(spec)
    return endpoint.open()


class _FrameWriter:
    """File-like sink pymavlink's encoder writes packed frames into."""

    def __init__(self, link: VehicleLink) -> None:
        self.link = link

    def write(self, frame: bytes) -> None:
        self.link.transmit(frame)


class VehicleLink:
    """The daemon's side of the conversation with one vehicle: where it is, and an encoder with
    its own sequence counter, so each vehicle sees an unbroken sequence of our frames."""

    def __init__(
        self,
        system_id: int,
        endpoint: Endpoint,
        address: Address | None,
        tlog: TlogWriter | None = None,
        on_send: Callable[[bytes], None] | None = None,
        source: tuple[int, int] | None = None,
    ) -> None:
        self.system_id = system_id
        self.endpoint = endpoint
        self.address = address if address is not None else endpoint.default_address()
        self.tlog = tlog
        self.on_send = on_send
        # our (system, component) on the wire: a ground station's unless told (a planner node
        # beside its autopilot may have its own, docs/onboard.md "On a companion computer")
        system, component = source or (GCS_SYSTEM_ID, GCS_COMPONENT_ID)
        self.mav = mavlink.MAVLink(_FrameWriter(self), system, component)
        self.frames_sent = 0

    def transmit(self, frame: bytes) -> None:
        """Send one packed frame to the vehicle and log it."""
        self.endpoint.send_to(frame, self.address)
        self.frames_sent += 1
        if self.tlog is not None:
            self.tlog.write(frame)

    def moved(self, endpoint: Endpoint, address: Address | None) -> None:
        """The vehicle was heard from another endpoint or address (e.g. it rebooted)."""
        self.endpoint = endpoint
        self.address = address if address is not None else endpoint.default_address()
