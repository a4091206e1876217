"""One endpoint per vehicle, against the real simulator: a UDP port per vehicle (PX4 style,
14540 + i) and a TCP connection per vehicle (ArduPilot SITL style, 5760 + 10 i)."""

from __future__ import annotations

import json
import os
import select
import socket
import subprocess
import threading
from pathlib import Path

import pytest
from loopback import free_port_block, run_swarmplan, start_swarmplan, stop

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402


def start_lockstep_sim(base: int, log: Path) -> subprocess.Popen:
    """The 2-UAV paper scenario, vehicle i sending to udp BASE + i, in lockstep."""
    return start_swarmplan(
        ["sim", "--scenario", "paper-2uav", "--seed", "1", "--lockstep", "--per-vehicle-ports",
         str(base), "--quiet"],
        log,
    )  # fmt: skip


def run_daemon(connect: list[str], out: Path) -> dict:
    args = [a for spec in connect for a in ("--connect", spec)]
    proc = run_swarmplan(
        ["daemon", *args, "--scenario", "paper-2uav", "--seed", "1", "--steps", "8",
         "--lockstep", "--timeout", "20", "--json", "--out", str(out)],
        timeout=90,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout)


@pytest.mark.timeout(120)
def test_one_udp_port_per_vehicle(tmp_path):
    base = free_port_block(2)
    sim = start_lockstep_sim(base, tmp_path / "sim.log")
    try:
        result = run_daemon([f"udpin:127.0.0.1:{base}", f"udpin:127.0.0.1:{base + 1}"], tmp_path)
    finally:
        stop(sim)
    assert result["steps"] == 8 and len(result["uavs"]) == 2
    assert str(base) in result["endpoints"] and str(base + 1) in result["endpoints"]
    assert all(u["distance_km"] > 4 for u in result["uavs"])  # both flew


class TcpVehicleServer(threading.Thread):
    """A SITL-like TCP server for one simulated vehicle: the vehicle's UDP frames go to the TCP
    client as a byte stream, and the client's stream is cut back into one frame per datagram."""

    def __init__(self, udp_port: int) -> None:
        super().__init__(daemon=True)
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.bind(("127.0.0.1", udp_port))
        self.udp.setblocking(False)
        self.server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.server.bind(("127.0.0.1", 0))
        self.server.listen(1)
        self.port = self.server.getsockname()[1]
        self.vehicle: tuple[str, int] | None = None
        self.done = threading.Event()

    def run(self) -> None:
        """Relay both ways as frames come (select: every datagram waiting, then the stream)."""
        client = None
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        while not self.done.is_set():
            ready, _, _ = select.select([self.udp, client or self.server], [], [], 0.05)
            if self.server in ready:
                client, _ = self.server.accept()
            if self.udp in ready:
                while True:
                    try:
                        data, self.vehicle = self.udp.recvfrom(65535)
                    except (BlockingIOError, OSError):
                        break
                    if client is not None:
                        try:
                            client.sendall(data)
                        except OSError:  # the daemon went: its end of the stream is closed
                            client.close()
                            client = None
            if client is not None and client in ready:
                try:
                    chunk = client.recv(65536)
                except OSError:
                    chunk = b""
                if chunk == b"":
                    client.close()
                    client = None
                elif self.vehicle is not None:
                    for msg in parser.parse_buffer(chunk) or ():
                        self.udp.sendto(msg.get_msgbuf(), self.vehicle)
        if client is not None:
            client.close()

    def stop(self) -> None:
        self.done.set()
        self.join(2)
        self.udp.close()
        self.server.close()


@pytest.mark.timeout(120)
def test_one_tcp_connection_per_vehicle(tmp_path):
    base = free_port_block(2)
    servers = [TcpVehicleServer(base + i) for i in range(2)]
    for s in servers:
        s.start()
    sim = start_lockstep_sim(base, tmp_path / "sim.log")
    try:
        result = run_daemon([f"tcp:127.0.0.1:{s.port}" for s in servers], tmp_path)
    finally:
        stop(sim)
        for s in servers:
            s.stop()
    assert result["steps"] == 8 and len(result["uavs"]) == 2
    assert all(f"tcp:127.0.0.1:{s.port}" in result["endpoints"] for s in servers)
    assert all(u["distance_km"] > 4 for u in result["uavs"])


def test_cli_port_in_use_is_one_line_exit_2(tmp_path):
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    holder.bind(("127.0.0.1", 0))
    port = holder.getsockname()[1]
    try:
        proc = run_swarmplan(
            ["daemon", "--connect", f"udpin:127.0.0.1:{port}", "--timeout", "1",
             "--out", str(tmp_path)],
            timeout=60,
        )  # fmt: skip
    finally:
        holder.close()
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and f"UDP port {port} is already in use" in lines[0], proc.stderr
