"""Real sockets between one simulated vehicle (``swarmplan sim --per-vehicle-ports BASE``: vehicle
i sends to BASE + i) and the daemon, that a test can watch and break:

* :class:`WatchingRelay` (UDP -> UDP): forwards both ways, keeps the vehicle's last heartbeat
  (mode, armed) and every mode it reported, and can send the vehicle a frame of its own (as
  another ground station would: a force disarm, a mode change).
* :class:`DroppableTcpBridge` (UDP -> TCP server, SITL-like): the daemon connects to it over TCP;
  ``drop()`` closes the connection and refuses new ones, ``restore()`` listens again on the same
  port.
"""

from __future__ import annotations

import contextlib
import os
import socket
import threading

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

FORCE_DISARM = 21196  # ArduPilot's magic param2 of a forced disarm
OTHER_GCS = 254  # the system id this test's own commands come from


def _parser() -> mavlink.MAVLink:
    p = mavlink.MAVLink(None)
    p.robust_parsing = True
    return p


class VehicleWatch:
    """What a vehicle said about itself in its heartbeats (autopilot component)."""

    def __init__(self) -> None:
        self.modes: list[int] = []  # every custom_mode reported, in order (changes only)
        self.mode: int | None = None
        self.armed: bool | None = None
        self.heartbeats = 0
        self.lock = threading.Lock()

    def see(self, data: bytes, parser: mavlink.MAVLink) -> None:
        for msg in parser.parse_buffer(data) or ():
            if msg.get_type() != "HEARTBEAT" or msg.get_srcComponent() != 1:
                continue
            with self.lock:
                self.heartbeats += 1
                self.mode = msg.custom_mode
                self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                if not self.modes or self.modes[-1] != msg.custom_mode:
                    self.modes.append(msg.custom_mode)


class WatchingRelay(threading.Thread):
    """Forwards one vehicle's datagrams to the daemon and back, watching its heartbeats."""

    def __init__(self, daemon_port: int, bind_port: int, sysid: int) -> None:
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", bind_port))
        self.sock.settimeout(0.05)
        self.daemon_addr = ("127.0.0.1", daemon_port)
        self.sysid = sysid
        self.vehicle_addr: tuple[str, int] | None = None
        self.watch = VehicleWatch()
        self.done = threading.Event()
        self.mav = mavlink.MAVLink(None, OTHER_GCS, 190)

    def run(self) -> None:
        parser = _parser()
        while not self.done.is_set():
            try:
                data, addr = self.sock.recvfrom(65535)
            except OSError:
                continue
            if addr[1] == self.daemon_addr[1]:
                if self.vehicle_addr is not None:
                    self.sock.sendto(data, self.vehicle_addr)
            else:
                self.vehicle_addr = addr
                self.watch.see(data, parser)
                with contextlib.suppress(OSError):  # the daemon is gone: keep watching
                    self.sock.sendto(data, self.daemon_addr)

    def command(self, command: int, *params: float) -> None:
        """A COMMAND_LONG to the vehicle's autopilot from another ground station."""
        assert self.vehicle_addr is not None, "the vehicle has not spoken yet"
        p = list(params) + [0.0] * (7 - len(params))
        frame = self.mav.command_long_encode(self.sysid, 1, command, 0, *p).pack(self.mav)
        self.sock.sendto(frame, self.vehicle_addr)

    def force_disarm(self) -> None:
        self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, FORCE_DISARM)

    def stop(self) -> None:
        self.done.set()
        self.join(2)
        self.sock.close()


class DroppableTcpBridge(threading.Thread):
    """A SITL-like TCP server for one simulated vehicle that a test can take down and bring back."""

    def __init__(self, udp_port: int) -> None:
        super().__init__(daemon=True)
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.bind(("127.0.0.1", udp_port))
        self.udp.settimeout(0.01)
        self.server: socket.socket | None = None
        self.port = 0
        self._listen()
        self.vehicle: tuple[str, int] | None = None
        self.done = threading.Event()
        self.down = threading.Event()
        self.connections = 0

    def _listen(self) -> None:
        server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        server.bind(("127.0.0.1", self.port))
        server.listen(1)
        server.settimeout(0.01)
        self.port = server.getsockname()[1]
        self.server = server

    def drop(self) -> None:
        """Close the daemon's connection and refuse new ones (the vehicle went away)."""
        self.down.set()

    def restore(self) -> None:
        """Listen again on the same port (the vehicle is back)."""
        self.down.clear()

    def run(self) -> None:
        client: socket.socket | None = None
        parser = _parser()
        while not self.done.is_set():
            if self.down.is_set():
                if client is not None:
                    client.close()
                    client = None
                if self.server is not None:
                    self.server.close()
                    self.server = None
            elif self.server is None:
                self._listen()
            if client is None and self.server is not None:
                try:
                    client, _ = self.server.accept()
                    client.settimeout(0.01)
                    self.connections += 1
                except OSError:
                    pass
            try:
                data, self.vehicle = self.udp.recvfrom(65535)
                if client is not None:
                    client.sendall(data)
            except OSError:
                pass
            if client is None:
                continue
            try:
                chunk = client.recv(65536)
            except (TimeoutError, BlockingIOError):
                chunk = None
            except OSError:
                chunk = b""
            if chunk == b"":
                client.close()
                client = None
            elif chunk and self.vehicle is not None:
                for msg in parser.parse_buffer(chunk) or ():
                    self.udp.sendto(msg.get_msgbuf(), self.vehicle)
        if client is not None:
            client.close()

    def stop(self) -> None:
        self.done.set()
        self.join(2)
        self.udp.close()
        if self.server is not None:
            self.server.close()
