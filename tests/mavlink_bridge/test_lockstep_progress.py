"""The daemon's lockstep clock waits for a slow simulator while its vehicles' clocks move, and
stops only once they stand still (mavlink_bridge/mission/lockstep_clock.py). A simulator of 300
vehicles on a busy machine took 31 s of wall time for one 10 s decision period, its clocks
moving all along, and the daemon had given up after 30 s. Here a vehicle built with pymavlink
plays that simulator (real UDP on loopback): granted time, it advances its clock one simulated
second every quarter of a wall second."""

from __future__ import annotations

import os
import socket
import threading
import time

os.environ.setdefault("MAVLINK20", "1")

import pytest  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402

from mavlink_bridge.mission.lockstep_clock import LockstepClock, LockstepError  # noqa: E402
from mavlink_bridge.vehicles.swarm_link import SwarmLink  # noqa: E402
from mavlink_bridge.vehicles.vehicle_key import VehicleKey  # noqa: E402

TICK_WALL_S = 0.25  # wall seconds per simulated second of the slow vehicle
WALL_TIMEOUT_S = 2.0  # the clock's limit without progress (8 ticks of the vehicle)
STEP_S = 20.0  # one period: 5 s of wall time for the slow vehicle, beyond WALL_TIMEOUT_S


class SlowLockstepVehicle(threading.Thread):
    """One fixed-wing vehicle in lockstep: it holds at the horizon granted (SYSTEM_TIME without
    UTC) and moves its clock towards it one second per ``TICK_WALL_S``, reporting its position
    each time; ``moves`` False: it never moves (a simulator that refuses the grants)."""

    def __init__(self, port: int, moves: bool = True) -> None:
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.02)
        self.station = ("127.0.0.1", port)
        self.mav = ml.MAVLink(None, srcSystem=1, srcComponent=1)
        self.moves = moves
        self.clock_ms = 0
        self.horizon_ms = 0
        self.stop = threading.Event()

    def send(self, msg: ml.MAVLink_message) -> None:
        self.sock.sendto(msg.pack(self.mav), self.station)

    def report(self) -> None:
        self.send(ml.MAVLink_heartbeat_message(
            ml.MAV_TYPE_FIXED_WING, ml.MAV_AUTOPILOT_ARDUPILOTMEGA,
            ml.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 15, ml.MAV_STATE_ACTIVE, 3))  # fmt: skip
        self.send(ml.MAVLink_global_position_int_message(
            self.clock_ms, -353632620, 1491652370, 584000, 500000, 0, 0, 0, 9000))  # fmt: skip

    def run(self) -> None:
        parser = ml.MAVLink(None)
        next_tick = time.monotonic()
        while not self.stop.is_set():
            try:
                data = self.sock.recv(65535)
            except TimeoutError:
                data = b""
            for msg in parser.parse_buffer(data) or []:
                if msg.get_type() == "SYSTEM_TIME" and msg.time_unix_usec == 0:
                    self.horizon_ms = max(self.horizon_ms, msg.time_boot_ms)
            if time.monotonic() >= next_tick:
                next_tick += TICK_WALL_S
                if self.moves and self.clock_ms < self.horizon_ms:
                    self.clock_ms = min(self.horizon_ms, self.clock_ms + 1000)
                self.report()
        self.sock.close()


def flown_one_period(moves: bool) -> tuple[float, int | None, str]:
    """Grant one period to a slow vehicle: the wall seconds it took, the time reached (None: the
    clock gave up) and what it said."""
    link = SwarmLink.open(["udpin:127.0.0.1:0"])
    vehicle = SlowLockstepVehicle(link.endpoints[0].port, moves)
    vehicle.start()
    try:
        heard = link.pump_until(lambda: VehicleKey(0, 1) in link.vehicles, 10.0)
        assert heard, "the vehicle was never heard"
        vehicles = [link.vehicles[VehicleKey(0, 1)]]
        link.pump_until(lambda: vehicles[0].has_position, 5.0)
        clock = LockstepClock(link, STEP_S, wall_timeout_s=WALL_TIMEOUT_S)
        clock.sync(vehicles)
        started = time.monotonic()
        try:
            reached: int | None = clock.advance(vehicles)
            said = ""
        except LockstepError as exc:
            reached, said = None, str(exc)
        return time.monotonic() - started, reached, said
    finally:
        vehicle.stop.set()
        vehicle.join(5)
        link.close()


@pytest.mark.timeout(60)
def test_a_simulator_slower_than_the_timeout_is_waited_for_while_its_clock_moves():
    took_s, reached, said = flown_one_period(moves=True)
    assert reached == STEP_S * 1000, said
    assert took_s > WALL_TIMEOUT_S  # the premise: the period took longer than the limit


@pytest.mark.timeout(60)
def test_a_simulator_whose_clock_stands_still_is_given_up_on():
    took_s, reached, said = flown_one_period(moves=False)
    assert reached is None and "did not reach simulated time 20 s" in said, said
    assert WALL_TIMEOUT_S <= took_s < 4 * WALL_TIMEOUT_S
