"""A daemon restarted after a long outage takes its planes back in whatever state they are in.

Real processes over loopback, signed: the simulator paced at 10x, the daemon killed (SIGKILL)
mid-mission, then an outage long enough for the simulator's GCS failsafe to fire (the planes
report MAV_STATE_CRITICAL), during which a "pilot" (this test, signed, never a heartbeat) sets
FS_LONG_TIMEOUT to 1 s so that the failsafe fires within a second of wall time, and changes
what the planes do; then the daemon resumed. Before: the resumed daemon waited for every plane
to report STANDBY or ACTIVE, and a plane that stays CRITICAL (inside a threat zone, range spent)
made it give up after --ready-timeout with exit 2 and ``steps: 0``.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from loopback import env, free_udp_port, start_swarmplan, stop
from pymavlink.dialects.v20 import ardupilotmega as ml
from reliability_harness import KEY_HEX, checkpoint_step, last_json, wait_until

from mavlink_wire import signing as bridge_signing
from planner.geodesy import geodetic_to_local_km, local_km_to_geodetic
from planner.hapf_aco import HapfAcoPlanner  # noqa: F401 - a checkpoint's classes, read fast
from planner.scenario import Origin

# 10x, not 20x: at 20x a step's computation must fit twice into 60 % of 0.5 s of wall time, and
# the daemon's calibration refused that time scale on a loaded machine (keeping_up.py)
SPEEDUP = 10
KEY = bytes.fromhex(KEY_HEX)
CIRCLE, RTL = 1, 11  # ArduPlane modes
THREAT = (20.0, 27.0, 6.0)  # x, y, radius (km)

SCENARIO = """
name = "resume-takeback"
steps = {steps}
threats_known = true

[parameters]
grid_nx = 40
grid_ny = 40
sensing_radius_km = 15.0
{range_line}

[uavs]
count = {count}
random_start = false
{starts}

[[targets]]
kind = "known_position"
x_km = 30
y_km = 30
value = 2

[[targets]]
kind = "unknown_position"
x_km = 10
y_km = 30
value = 1

[[threats]]
x_km = {tx}
y_km = {ty}
radius_km = {tr}
"""

START = "[[uavs.start]]\nx_km = {x}\ny_km = {y}\nheading_deg = {h}\n"


def _scenario(tmp_path: Path, steps: int, starts: list[tuple], range_km: float | None) -> Path:
    path = tmp_path / "resume-takeback.toml"
    path.write_text(
        SCENARIO.format(
            steps=steps,
            range_line="" if range_km is None else f"max_range_km = {range_km}",
            count=len(starts),
            starts="\n".join(START.format(x=x, y=y, h=h) for x, y, h in starts),
            tx=THREAT[0],
            ty=THREAT[1],
            tr=THREAT[2],
        )
    )
    return path




class _Pilot:
    """A second ground station on the dead daemon's port while it is down: hears the planes
    (status, mode, position) and sends them signed commands, but never a heartbeat (so their
    GCS failsafe still fires)."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.sock.settimeout(0.05)
        self.mav = ml.MAVLink(None, 250, 190)
        bridge_signing.sign_outgoing(self.mav, KEY, 3)
        self.addr: dict[int, tuple] = {}
        self.status: dict[int, int] = {}
        self.mode: dict[int, int] = {}
        self.xy_km: dict[int, np.ndarray] = {}
        self.params: dict[tuple[int, str], float] = {}

    def pump(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        parser = ml.MAVLink(None)
        while time.monotonic() < end:
            try:
                data, addr = self.sock.recvfrom(65535)
            except TimeoutError:
                continue
            for msg in parser.parse_buffer(data) or ():
                sid = msg.get_srcSystem()
                if msg.get_srcComponent() != 1:
                    continue
                self.addr[sid] = addr
                if msg.get_type() == "HEARTBEAT":
                    self.status[sid], self.mode[sid] = msg.system_status, msg.custom_mode
                elif msg.get_type() == "PARAM_VALUE":
                    self.params[(sid, msg.param_id)] = msg.param_value
                elif msg.get_type() == "GLOBAL_POSITION_INT":
                    x, y = geodetic_to_local_km(msg.lat / 1e7, msg.lon / 1e7, Origin())
                    self.xy_km[sid] = np.array([x[0], y[0]])

    def send(self, sid: int, msg: ml.MAVLink_message) -> None:
        frame = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        self.sock.sendto(frame, self.addr[sid])

    def param(self, sid: int, name: str, value: float, ptype: int) -> None:
        self.send(sid, ml.MAVLink_param_set_message(sid, 1, name.encode(), value, ptype))

    def set_mode(self, sid: int, mode: int) -> None:
        self.send(sid, ml.MAVLink_set_mode_message(sid, ml.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode))

    def fly_to(self, sid: int, x_km: float, y_km: float) -> None:
        lat, lon = local_km_to_geodetic(np.array([x_km]), np.array([y_km]), Origin())
        self.send(
            sid,
            ml.MAVLink_command_int_message(
                sid, 1, ml.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, ml.MAV_CMD_DO_REPOSITION, 0, 0,
                -1, 1, 0, 0, round(lat[0] * 1e7), round(lon[0] * 1e7), 500,
            ),
        )  # fmt: skip

    def close(self) -> None:
        self.sock.close()


class _Mission:
    """The simulator and the daemon of one scenario file, the daemon killed and resumed."""

    def __init__(self, tmp_path: Path, scenario: Path, steps: int, vehicles: int) -> None:
        self.port = free_udp_port()
        key_file = tmp_path / "mission.key"
        key_file.write_text(KEY_HEX + "\n")
        self.ckpt = tmp_path / "daemon.ckpt"
        self.out = tmp_path / "out"
        self.sim_log, self.log = tmp_path / "sim.log", tmp_path / "daemon.log"
        self.sim = start_swarmplan(
            ["sim", "--scenario", str(scenario), "--seed", "3", "--speedup", str(SPEEDUP),
             "--gcs-port", str(self.port), "--boot-s", "2", "--quiet"],
            self.sim_log,
            env(SWARMPLAN_SIGNING_KEY=KEY_HEX),
        )  # fmt: skip
        self.args = [
            "daemon", "--connect", f"udpin:127.0.0.1:{self.port}", "--scenario", str(scenario),
            "--seed", "3", "--expect", str(vehicles), "--steps", str(steps),
            "--time-scale", str(SPEEDUP), "--timeout", "30", "--ready-timeout", "8",
            "--lost-after", "5", "--signing-key-file", str(key_file),
            "--checkpoint", str(self.ckpt), "--out", str(self.out), "--no-view",
            "--rtl-watch", "0",
        ]  # fmt: skip
        self.procs: list[subprocess.Popen] = [self.sim]

    def kill_after_step(self, step: int) -> int:
        first = start_swarmplan(self.args, self.log)
        self.procs.append(first)
        assert wait_until(lambda: checkpoint_step(self.ckpt) >= step, 40, [first, self.sim]), (
            self.log.read_text()[-2000:]
        )
        os.kill(first.pid, signal.SIGKILL)
        first.wait(5)
        return checkpoint_step(self.ckpt)

    def resume(self) -> tuple[subprocess.Popen, float]:
        """The daemon restarted with --resume; the wall seconds to its first decision."""
        with open(self.log, "a") as f:
            f.write("\n--- killed, restarting ---\n")
        started = time.monotonic()
        second = start_swarmplan([*self.args, "--resume"], self.log)
        self.procs.append(second)
        # (its progress line: the first decision after the restart)
        wait_until(lambda: "\rstep " in self.resumed_log(), 40, [second])
        return second, time.monotonic() - started

    def result(self) -> dict:
        return json.loads((self.out / "result.json").read_text())

    def resumed_log(self) -> str:
        return self.log.read_text().split("--- killed, restarting ---")[1]

    def stop(self) -> None:
        for proc in reversed(self.procs):
            stop(proc)


def _decisions(result: dict) -> dict[int, dict]:
    return {d["vehicle"]: d for d in result.get("resume_decisions", [])}


@pytest.mark.timeout(120)
def test_a_resumed_daemon_takes_back_planes_in_failsafe_rtl_or_a_threat(tmp_path: Path):
    """Three planes after the outage: 1 circles its last target in the GCS failsafe, 2 was
    switched to CIRCLE and the failsafe made that RTL, 3 was flown into the threat with its
    fence off (CRITICAL for as long as it is inside). 1 and 2 are re-guided and
    fly the mission to its last step; 3 is sent home along the safe way out."""
    steps = 8
    starts = [(8.5, 8.5, 45), (31.5, 8.5, 135), (20.5, 16.5, 0)]
    scenario = _scenario(tmp_path, steps, starts, None)
    mission = _Mission(tmp_path, scenario, steps, len(starts))
    pilot = None
    try:
        killed = mission.kill_after_step(2)
        outage_start = time.monotonic()
        pilot = _Pilot(mission.port)
        pilot.pump(0.5)
        assert sorted(pilot.addr) == [1, 2, 3], pilot.addr

        def switched() -> bool:
            """2 in CIRCLE (the failsafe, when it fires, makes that RTL), 3's fence off (before
            the daemon's 5 s FS_LONG_TIMEOUT is up; asked again until it shows)."""
            if pilot.mode.get(2) != CIRCLE:
                pilot.set_mode(2, CIRCLE)
            if pilot.params.get((3, "FENCE_ENABLE")) != 0.0:
                pilot.param(3, "FENCE_ENABLE", 0.0, ml.MAV_PARAM_TYPE_INT8)
            pilot.pump(0.2)
            return pilot.mode.get(2) == CIRCLE and pilot.params.get((3, "FENCE_ENABLE")) == 0.0

        assert wait_until(switched, 4, [mission.sim]), (pilot.mode, pilot.params)

        def failsafe_took_them() -> bool:
            for sid in (1, 2, 3):
                if pilot.params.get((sid, "FS_LONG_TIMEOUT")) != 1.0:
                    pilot.param(sid, "FS_LONG_TIMEOUT", 1.0, ml.MAV_PARAM_TYPE_REAL32)
            pilot.fly_to(3, THREAT[0], THREAT[1])
            pilot.pump(0.3)
            inside = np.hypot(*(pilot.xy_km.get(3, np.zeros(2)) - THREAT[:2])) < THREAT[2] - 2
            critical = all(pilot.status.get(s) == ml.MAV_STATE_CRITICAL for s in (1, 2, 3))
            return critical and pilot.mode.get(2) == RTL and bool(inside)

        assert wait_until(failsafe_took_them, 20, [mission.sim]), (
            pilot.status, pilot.mode, pilot.xy_km.get(3),
        )  # fmt: skip
        pilot.close()
        pilot = None
        outage_s = time.monotonic() - outage_start
        second, resume_s = mission.resume()
        second.wait(90)
    finally:
        if pilot is not None:
            pilot.close()
        mission.stop()
    assert second.returncode == 0, mission.log.read_text()[-3000:]
    result = mission.result()
    print(
        f"\nkilled after step {killed}; outage {outage_s:.1f} s wall; "
        f"resume to the first step {resume_s:.1f} s"
    )
    assert result["resumed_from_step"] == killed
    assert result["steps"] == steps  # the mission flew to its last step
    decisions = _decisions(result)
    assert decisions[1]["decision"] == "continue", decisions
    assert decisions[2]["decision"] == "continue" and decisions[2]["mode"] == "RTL", decisions
    assert decisions[3]["decision"] == "home" and "threats[0]" in decisions[3]["why"], decisions
    assert decisions[3]["status"] == "CRITICAL"
    log = mission.resumed_log()
    for sid in (1, 2, 3):  # one line per plane says which and why
        assert len([ln for ln in log.splitlines() if f"resume: vehicle {sid} (" in ln]) == 1, log
    # 3 is out of the mission for good; 1 and 2 were never lost after the resume
    events = [e for e in result["link_events"] if e["step"] > killed]
    assert [e["uav"] for e in events if e["event"] == "lost"] == [2], events
    assert not [e for e in events if e["event"] == "rejoined" and e["uav"] == 2], events


@pytest.mark.timeout(120)
def test_a_plane_whose_range_is_spent_is_sent_home_not_waited_for(tmp_path: Path):
    """A small L_max: the outage spends the plane's range, the simulator's battery failsafe
    sends it home (RTL, CRITICAL for good). The resumed daemon says it cannot continue and why
    (the battery's account), leaves it on its way home, and ends the mission there (no plane
    left to fly it) with exit 0 and the steps flown before the outage."""
    steps = 30
    scenario = _scenario(tmp_path, steps, [(12.5, 10.5, 0)], 16.0)
    mission = _Mission(tmp_path, scenario, steps, 1)
    pilot = None
    try:
        killed = mission.kill_after_step(2)
        pilot = _Pilot(mission.port)
        pilot.pump(0.3)

        def range_spent() -> bool:
            if pilot.params.get((1, "FS_LONG_TIMEOUT")) != 1.0:
                pilot.param(1, "FS_LONG_TIMEOUT", 1.0, ml.MAV_PARAM_TYPE_REAL32)
            pilot.pump(0.3)
            return pilot.status.get(1) == ml.MAV_STATE_CRITICAL and pilot.mode.get(1) == RTL

        assert wait_until(range_spent, 25, [mission.sim]), (pilot.status, pilot.mode)
        # (FS_LONG_ACTN 0 keeps GUIDED in the GCS failsafe: RTL is the battery failsafe's)
        pilot.close()
        pilot = None
        second, _ = mission.resume()
        second.wait(60)
    finally:
        if pilot is not None:
            pilot.close()
        mission.stop()
    assert second.returncode == 0, mission.log.read_text()[-3000:]
    result = mission.result()
    decision = _decisions(result)[1]
    assert decision["decision"] == "home" and "range spent" in decision["why"], decision
    assert "battery" in decision["why"] and decision["status"] == "CRITICAL"
    assert result["ended"].startswith("completed at the resume"), result["ended"]
    assert result["steps"] == killed
    summary = last_json(mission.sim_log)
    assert summary is not None and summary["fence_breaches"] == 0
