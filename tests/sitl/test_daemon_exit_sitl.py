"""The daemon against real ArduPlane SITL (``ARDUPLANE_SITL``): one plane's failure stays one
plane's, and SIGTERM sends RTL to every airborne plane. What each plane does is read from its
own heartbeats on its second MAVLink port (SERIAL1), not from the daemon. Lean on purpose: 10x,
50 s decision steps of tests/sitl/arduplane-small.toml, a few steps each."""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from loopback import start_swarmplan, stop  # noqa: E402
from pymavlink import mavutil  # noqa: E402
from sitl_harness import SitlVehicle, _listening, homes_for_scenario  # noqa: E402

from planner.scenario import load_scenario  # noqa: E402

SCENARIO = Path(__file__).with_name("arduplane-small.toml")
SPEEDUP = 10
GUIDED, RTL = 15, 11


class HeartbeatWatch(threading.Thread):
    """Connects to a plane's SERIAL1 (once it has booted) and keeps every mode its autopilot
    reports in its heartbeats."""

    def __init__(self, vehicle: SitlVehicle) -> None:
        super().__init__(daemon=True)
        self.vehicle = vehicle
        self.modes: list[int] = []
        self.done = threading.Event()

    def run(self) -> None:
        conn = None
        while not self.done.is_set():
            if conn is None:
                if not _listening(self.vehicle.payload_port):  # booted: SERIAL1 listens
                    time.sleep(0.2)
                    continue
                try:
                    conn = mavutil.mavlink_connection(
                        self.vehicle.payload, source_system=250, autoreconnect=False
                    )
                except OSError:
                    time.sleep(0.2)
                    continue
            try:
                msg = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.2)
            except (OSError, ConnectionError):
                break  # the plane is gone
            if msg is None or msg.get_srcComponent() != 1:
                continue
            mine = msg.get_srcSystem() == self.vehicle.system_id
            if mine and (not self.modes or self.modes[-1] != msg.custom_mode):
                self.modes.append(msg.custom_mode)
        if conn is not None:
            conn.close()

    @property
    def mode(self) -> int | None:
        return self.modes[-1] if self.modes else None

    def stop(self) -> None:
        self.done.set()
        self.join(3)


def wait_for(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.1)
    return predicate()


def start_daemon(swarm, steps: int, out: Path, *extra: str) -> tuple:
    log = out / "daemon.log"
    proc = start_swarmplan(
        ["daemon", *swarm.connect_args(), "--scenario", str(SCENARIO), "--expect",
         str(len(swarm.vehicles)), "--steps", str(steps), "--time-scale", str(SPEEDUP),
         "--airspeed-range", "22:30", "--timeout", "30", "--no-view", "--out", str(out), *extra],
        log,
    )  # fmt: skip
    return proc, log


def watch(swarm) -> list[HeartbeatWatch]:
    watches = [HeartbeatWatch(v) for v in swarm.vehicles]
    for w in watches:
        w.start()
    return watches


def decision_clocks(tlog: Path, system_id: int) -> list[int]:
    """The vehicle's own clock (time_boot_ms of its newest GLOBAL_POSITION_INT) as each decision
    step's guided target to it went out, read from the daemon's tlog (what went over the wire);
    a step's resent command (every 0.3 s of wall time) is folded into its step."""
    log = mavutil.mavlink_connection(str(tlog))
    clock, last, out = 0, None, []
    while True:
        msg = log.recv_match(type=["GLOBAL_POSITION_INT", "COMMAND_INT"])
        if msg is None:
            break
        if msg.get_type() == "GLOBAL_POSITION_INT" and msg.get_srcSystem() == system_id:
            clock = max(clock, msg.time_boot_ms)
        elif (
            msg.get_type() == "COMMAND_INT"
            and msg.target_system == system_id
            and msg.command == mavutil.mavlink.MAV_CMD_DO_REPOSITION
        ):
            if last is None or clock - last > 10_000:
                out.append(clock)
            last = clock
    log.close()
    return out


def reached_step(log: Path, step: int) -> bool:
    return re.search(rf"step +{step}/", log.read_text(errors="replace")) is not None


@pytest.mark.timeout(180)
def test_one_plane_killed_mid_mission_the_others_finish_and_return(sitl_swarm, tmp_path):
    homes = homes_for_scenario(load_scenario(str(SCENARIO)), 1)
    swarm = sitl_swarm(homes, speedup=SPEEDUP, params={"FENCE_ENABLE": 0})
    # RTL at the mission's end without the watch of the flight home (the planes' own
    # heartbeats below say they return)
    daemon, log = start_daemon(swarm, 4, tmp_path, "--rtl-watch", "0")
    watches = watch(swarm)
    try:
        assert wait_for(lambda: reached_step(log, 1), 120), log.read_text()[-2000:]
        swarm.kill(2)  # plane 3: SIGKILL, its TCP connection closes
        assert daemon.wait(120) == 0, log.read_text()[-2000:]
        # planes 1 and 2 say RTL in their own heartbeats (1 Hz of their clock)
        assert wait_for(lambda: all(w.mode == RTL for w in watches[:2]), 10), [
            w.modes for w in watches
        ]
    finally:
        stop(daemon)
        for w in watches:
            w.stop()
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["ended"] == "completed" and result["steps"] == 4
    assert result["lost_uavs"] == [2]
    lost = next(e for e in result["link_events"] if e["event"] == "lost")
    assert lost["uav"] == 2 and "tcp:127.0.0.1:" in lost["reason"]
    assert result["rtl_sent_to"] == [1, 2] and "3" in result["rtl_not_sent"]
    assert all(GUIDED in w.modes for w in watches)  # all three flew the mission
    # paced by the planes' own clock: a decision every 50 s of it; a gap over 1.5 steps is a
    # stall or a late step, and is counted (paced by the wall clock, steps were 51.7-63 s of
    # the planes' time and late_steps said 0)
    gaps_s = np.diff(decision_clocks(tmp_path / "mission.tlog", 1)) / 1e3
    print("plane 1, vehicle seconds between decisions:", gaps_s, "late", result["late_steps"])
    assert len(gaps_s) == 4, gaps_s
    assert result["late_steps"] >= int((gaps_s > 75.0).sum()), (gaps_s, result["late_steps"])


@pytest.mark.timeout(180)
def test_sigterm_sends_rtl_to_every_airborne_plane_and_writes_the_result(sitl_swarm, tmp_path):
    homes = homes_for_scenario(load_scenario(str(SCENARIO)), 1)[:2]
    swarm = sitl_swarm(homes, speedup=SPEEDUP, params={"FENCE_ENABLE": 0})
    daemon, log = start_daemon(swarm, 8, tmp_path)
    watches = watch(swarm)
    try:
        assert wait_for(lambda: reached_step(log, 2), 120), log.read_text()[-2000:]
        assert all(w.mode == GUIDED for w in watches), [w.modes for w in watches]
        daemon.send_signal(signal.SIGTERM)
        status = daemon.wait(60)
        assert wait_for(lambda: all(w.mode == RTL for w in watches), 10), [w.modes for w in watches]
    finally:
        stop(daemon)
        for w in watches:
            w.stop()
    assert status == 143, log.read_text()[-2000:]
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["ended"] == "interrupted (SIGTERM)" and result["rtl_sent_to"] == [1, 2]
    assert 2 <= result["steps"] < 8
    assert (tmp_path / "paths.png").exists() and (tmp_path / "mission.tlog").exists()
