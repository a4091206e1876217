"""MAVLink 2 over UDP for the simulated vehicles: a per-datagram parser, a sender per component
and the socket of one vehicle.

Parsing: each datagram is parsed on its own, so a bad datagram never costs the next good one
(pymavlink's stream parser carries a partial junk frame over into the next datagram). Inside a
datagram, frames are found by scanning for the MAVLink start bytes and decoding exactly one
frame's length at each; a frame that fails (bad CRC, bad length) is counted and the scan resumes
one byte after its start, so junk in front of a good frame does not swallow it either. Frames of
message ids this dialect does not know (``UNKNOWN_<id>``) cannot be CRC-checked: they are counted,
dropped and rescanned like junk.

Ports: a vehicle *sends* like a pymavlink ``udpout`` (its own socket to a fixed destination, the
ground station's / daemon's port) and answers whatever comes back to that socket; see
docs/simulator.md for the conventions.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")  # pymavlink reads it once per process, at import

import socket  # noqa: E402
from dataclasses import dataclass, field, fields  # noqa: E402

from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

MAGIC_V2 = mavlink.PROTOCOL_MARKER_V2  # 0xFD
MAGIC_V1 = mavlink.PROTOCOL_MARKER_V1  # 0xFE
MAX_DATAGRAM = 65535
MAV_COMP_ID_AUTOPILOT1 = mavlink.MAV_COMP_ID_AUTOPILOT1  # 1
MAV_COMP_ID_CAMERA = mavlink.MAV_COMP_ID_CAMERA  # 100


def peer_of(message: mavlink.MAVLink_message) -> tuple[int, int]:
    """(sysid, compid) of a message's sender: whom an answer is addressed to."""
    return message.get_srcSystem(), message.get_srcComponent()


@dataclass
class LinkStats:
    """Counters of everything received, shared by all vehicles of a simulator."""

    datagrams: int = 0
    frames: int = 0
    bad_datagrams: int = 0  # datagrams with at least one bad byte run or bad frame
    bad_frames: int = 0  # CRC / length failures and junk byte runs
    unknown_messages: int = 0  # UNKNOWN_<id> frames, dropped
    duplicates: int = 0  # the same frame delivered to several vehicle sockets
    rejected_commands: int = 0  # commands or values refused as out of range / unsupported
    ignored_messages: int = 0  # good frames no vehicle had a use for
    stale_commands: int = 0  # commands overtaken by a newer one from the same sender (reordered)
    sent: int = 0
    by_type: dict[str, int] = field(default_factory=dict)  # good frames by message type

    def counts(self) -> dict[str, int]:
        """Every counter but ``by_type``, by name (the simulator's summary)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "by_type"}


class DatagramParser:
    """Turns one UDP datagram into the good MAVLink messages in it, counting the rest."""

    def __init__(self, stats: LinkStats) -> None:
        self._mav = mavlink.MAVLink(None)
        self.stats = stats
        #: with MAVLink signing on (sim_gateway/signing.py): ``accept(frame, msg_id) -> bool``;
        #: a refused frame is skipped whole (it is counted there) and never handled
        self.signature_check = None

    def parse(self, data: bytes) -> list[mavlink.MAVLink_message]:
        """Good messages of one datagram, in order; the parser keeps nothing between calls."""
        stats = self.stats
        stats.datagrams += 1
        good: list[mavlink.MAVLink_message] = []
        bad = 0
        pos, end = 0, len(data)
        junk_run = False
        while pos < end:
            magic = data[pos]
            if magic == MAGIC_V2 and pos + 3 <= end:
                signed = data[pos + 2] & mavlink.MAVLINK_IFLAG_SIGNED
                length = (
                    10 + data[pos + 1] + 2 + (mavlink.MAVLINK_SIGNATURE_BLOCK_LEN if signed else 0)
                )
            elif magic == MAGIC_V1 and pos + 2 <= end:
                length = 6 + data[pos + 1] + 2
            else:
                if not junk_run:
                    bad += 1
                    junk_run = True
                pos += 1
                continue
            message = None
            if pos + length <= end:
                try:
                    message = self._mav.decode(bytearray(data[pos : pos + length]))
                except (mavlink.MAVError, IndexError, ValueError, TypeError, UnicodeError):
                    message = None
            if message is None:
                if not junk_run:
                    bad += 1
                    junk_run = True
                pos += 1
                continue
            if message.get_type().startswith("UNKNOWN"):
                # no CRC check is possible: drop it, and rescan its bytes in case it was junk
                # in front of a good frame
                stats.unknown_messages += 1
                bad += 1
                junk_run = True
                pos += 1
                continue
            junk_run = False
            frame = data[pos : pos + length]
            pos += length
            check = self.signature_check
            if check is not None and not check.accept(bytes(frame), message.get_msgId()):
                continue
            good.append(message)
        stats.frames += len(good)
        if bad:
            stats.bad_datagrams += 1
            stats.bad_frames += bad
        return good


class ComponentSender:
    """Packs messages as one (system, component), with that component's own sequence counter."""

    def __init__(self, system_id: int, component_id: int) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)

    def pack(self, message: mavlink.MAVLink_message) -> bytes:
        buf = message.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        self.mav.total_packets_sent += 1
        return bytes(buf)


def station_address(ip: str, port: int) -> tuple[str, int]:
    """The address replies from a ground station at ``ip:port`` come from: itself, but for
    0.0.0.0, which sends to this host, whose replies come from 127.0.0.1."""
    return ("127.0.0.1" if ip == "0.0.0.0" else ip, port)


class VehicleSocket:
    """The UDP socket of one vehicle: sends to its ground-station address, receives replies."""

    def __init__(
        self, bind_host: str, bind_port: int, destination: tuple[str, int], stats: LinkStats
    ):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        self.sock.bind((bind_host, bind_port))
        self.sock.setblocking(False)
        self.destination = destination  # (IPv4 address, port)
        #: the ground station this vehicle is bound to: the address its replies come from
        self.station = station_address(*destination)
        self.stats = stats

    @property
    def local_port(self) -> int:
        return int(self.sock.getsockname()[1])

    def send(self, buf: bytes) -> None:
        try:
            self.sock.sendto(buf, self.destination)
            self.stats.sent += 1
        except OSError:
            pass  # nobody listening yet (ICMP refused) or buffer full: a radio link loses it too

    def receive_all(self, limit: int = 256) -> list[tuple[bytes, tuple[str, int]]]:
        """Datagrams waiting on the socket (at most ``limit``), each with its sender's address."""
        out = []
        for _ in range(limit):
            try:
                data, addr = self.sock.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break  # e.g. ECONNREFUSED reported for an earlier send
            out.append((data, addr[:2]))
        return out

    def close(self) -> None:
        self.sock.close()
