"""The simulator test harness: a simulator running in a thread on loopback UDP, a pymavlink
ground station bound to a free port (port 0) that the simulator sends to, and take-off."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import threading  # noqa: E402
import time  # noqa: E402

from pymavlink import mavutil  # noqa: E402

from planner.scenario import load_scenario  # noqa: E402
from sim_gateway.simulator import SimOptions, Simulator  # noqa: E402


class GroundStation:
    """A pymavlink udpin endpoint (sysid 255) with small helpers that wait with a deadline."""

    def __init__(self) -> None:
        self.conn = mavutil.mavlink_connection(
            "udpin:127.0.0.1:0", source_system=255, source_component=190
        )
        self.port = self.conn.port.getsockname()[1]
        self.mav = self.conn.mav

    def ensure_peer(self) -> None:
        """A udpin socket can only send once it has heard a vehicle: wait for one."""
        if not self.conn.clients:
            self.wait("HEARTBEAT", timeout=5)

    def heartbeat(self) -> None:
        self.ensure_peer()
        self.mav.heartbeat_send(
            mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
        )

    def wait(
        self,
        mtype: str | list[str],
        sysid: int | None = None,
        timeout: float = 5.0,
        compid=None,
        cond=None,
    ):
        """The next message of a type from a system, or None at the deadline."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            m = self.conn.recv_match(type=mtype, blocking=True, timeout=0.1)
            if m is None:
                continue
            if sysid is not None and m.get_srcSystem() != sysid:
                continue
            if compid is not None and m.get_srcComponent() != compid:
                continue
            if cond is not None and not cond(m):
                continue
            return m
        return None

    def drain(self) -> None:
        while self.conn.recv_match(blocking=False) is not None:
            pass

    def command_long(
        self, sysid: int, command: int, *params: float, comp: int = 1, timeout: float = 5.0
    ):
        p = list(params) + [0.0] * (7 - len(params))
        self.ensure_peer()
        self.mav.command_long_send(sysid, comp, command, 0, *p)
        return self.wait("COMMAND_ACK", sysid, timeout, cond=lambda m: m.command == command)

    def command_int(
        self, sysid: int, command: int, frame: int, p1=0.0, p2=0.0, p3=0.0, p4=0.0, x=0, y=0, z=0.0
    ):
        self.ensure_peer()
        self.mav.command_int_send(sysid, 1, frame, command, 0, 0, p1, p2, p3, p4, x, y, z)
        return self.wait("COMMAND_ACK", sysid, cond=lambda m: m.command == command)

    def close(self) -> None:
        self.conn.close()


class RunningSim:
    """A Simulator running in a background thread until closed."""

    def __init__(self, sim: Simulator) -> None:
        self.sim = sim
        self.stop = threading.Event()
        self.thread = threading.Thread(target=sim.run, kwargs={"stop": self.stop}, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=10)
        self.sim.close()


def start_sim(port: int, scenario: str = "paper-2uav", **options) -> RunningSim:
    opts = {"boot_s": 0.0, "speedup": 10.0} | options
    return RunningSim(Simulator(load_scenario(scenario), SimOptions(gcs_port=port, **opts)))


def take_off(gcs: GroundStation, sysid: int = 1, alt_wait: float = 20.0) -> None:
    """Arm in TAKEOFF mode and wait until airborne (used by several tests)."""
    gcs.heartbeat()
    assert gcs.command_long(sysid, 176, 1, 13).result == 0
    assert gcs.command_long(sysid, 400, 1).result == 0
    assert gcs.wait("GLOBAL_POSITION_INT", sysid, alt_wait, cond=lambda m: m.relative_alt > 20_000)
