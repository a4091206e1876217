"""Believing only what is authentic (issue 12, findings 5-7): a real simulator and a real daemon
over loopback UDP, and a stranger's socket sending as the vehicles. With signing on, nothing
unsigned changes anything (no reply address moves, no vehicle is kept alive, no time or position
is taken); without signing, frames of a vehicle heard from a second address, implausible frames
and frames with extreme values are dropped and counted, never believed, and nothing crashes."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import contextlib  # noqa: E402
import json  # noqa: E402
import signal  # noqa: E402
import socket  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from loopback import env, free_udp_port, start_swarmplan, stop  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402
from reliability_harness import KEY_HEX, last_json  # noqa: E402
from udp_fault_relay import FaultProfile, FaultRelay  # noqa: E402

from mavlink_bridge.mission.daemon import DaemonOptions, MissionDaemon  # noqa: E402
from planner.geodesy import local_km_to_geodetic  # noqa: E402
from planner.scenario import load_scenario  # noqa: E402

SCENARIO = "paper-10uav"
STEPS = 8
NO_VIOLATIONS = {"threat": 0, "separation": 0, "turn": 0, "range": 0}


class Spoofer(threading.Thread):
    """A stranger on its own UDP socket: sends ``make(k)`` (one datagram, or None to skip) to the
    daemon's port every ``period_s`` until stopped, and counts every datagram sent back to it."""

    def __init__(self, port: int, make: Callable[[int], bytes | None], period_s: float) -> None:
        super().__init__(daemon=True, name="spoofer")
        self.target = ("127.0.0.1", port)
        self.make = make
        self.period_s = period_s
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.sent = 0
        self.received = 0
        self.received_types: dict[str, int] = {}
        self._halt = threading.Event()

    def run(self) -> None:
        k = 0
        while not self._halt.is_set():
            data = self.make(k)
            k += 1
            if data is not None:
                try:
                    self.sock.sendto(data, self.target)
                    self.sent += 1
                except OSError:
                    pass
            while True:
                try:
                    reply = self.sock.recv(65535)
                except (BlockingIOError, ConnectionRefusedError):
                    break
                self.received += 1
                for msg in ml.MAVLink(None).parse_buffer(reply) or ():
                    kind = msg.get_type()
                    self.received_types[kind] = self.received_types.get(kind, 0) + 1
            self._halt.wait(self.period_s)

    def stop(self) -> None:
        self._halt.set()
        self.join(5)
        self.sock.close()


def pack(msg: ml.MAVLink_message, sysid: int, compid: int = 1, seq: int = 0) -> bytes:
    mav = ml.MAVLink(None, sysid, compid)
    mav.seq = seq % 256
    return bytes(msg.pack(mav))


def fly_with_spoofer(
    tmp_path: Path,
    make: Callable[[int], bytes | None],
    *,
    signed: bool,
    period_s: float = 0.0005,
    steps: int = STEPS,
    seed: int = 3,
) -> tuple[dict, dict | None, Spoofer, str]:
    """A lockstep mission of ``steps`` steps (simulator and daemon as processes) while a spoofer
    sends ``make(k)`` to the daemon's port; returns the daemon's result, the simulator's summary,
    the spoofer and the daemon's log."""
    port = free_udp_port()
    key_file = tmp_path / "mission.key"
    key_file.write_text(KEY_HEX + "\n")
    sim_log, daemon_log = tmp_path / "sim.log", tmp_path / "daemon.log"
    sim_env = env(SWARMPLAN_SIGNING_KEY=KEY_HEX) if signed else env()
    sim = start_swarmplan(
        ["sim", "--scenario", SCENARIO, "--seed", str(seed), "--lockstep", "--speedup", "100",
         "--gcs-port", str(port), "--quiet"],
        sim_log,
        sim_env,
    )  # fmt: skip
    args = [
        "daemon", "--connect", f"udpin:127.0.0.1:{port}", "--scenario", SCENARIO,
        "--seed", str(seed), "--steps", str(steps), "--lockstep", "--timeout", "30",
        "--out", str(tmp_path / "out"), "--json",
    ]  # fmt: skip
    if signed:
        args += ["--signing-key-file", str(key_file)]
    daemon = start_swarmplan(args, daemon_log, stdout_pipe=True)
    spoofer = Spoofer(port, make, period_s)
    spoofer.start()
    try:
        stdout, _ = daemon.communicate(timeout=150)
    finally:
        spoofer.stop()
        stop(daemon)
        stop(sim)
    log = daemon_log.read_text(errors="replace")
    assert "Traceback" not in log, log[-3000:]
    assert daemon.returncode == 0, log[-3000:]
    return json.loads(stdout), last_json(sim_log), spoofer, log


@pytest.mark.timeout(200)
def test_unsigned_radio_status_changes_nothing_when_signing_is_on(tmp_path: Path):
    """Finding 5: unsigned RADIO_STATUS (accepted unsigned, as ArduPilot does) from system 3
    diverted the daemon's signed commands for vehicle 3 to the sender."""
    radio = ml.MAVLink_radio_status_message(200, 190, 50, 10, 10, 0, 0)
    frames = [pack(radio, 3, 1, k) for k in range(256)]
    result, summary, spoofer, _ = fly_with_spoofer(tmp_path, lambda k: frames[k % 256], signed=True)
    assert spoofer.sent > 2000
    assert spoofer.received == 0, spoofer.received_types  # no frame for vehicle 3 diverted
    assert result["steps"] == STEPS and result["lost_uavs"] == []
    assert result["violations"] == NO_VIOLATIONS
    trust = result["plausibility"]
    # counted while the mission ran (the spoofer starts before it and ends after its result)
    assert 1000 < trust["unsigned_ignored"] <= spoofer.sent
    assert trust["second_address"] == 0  # not even looked at: unsigned never reaches the rules
    assert summary is not None and summary["fence_breaches"] == 0


@pytest.mark.timeout(200)
def test_a_position_with_time_boot_ms_0xffffffff_does_not_crash_the_daemon(tmp_path: Path):
    """Finding 6: GLOBAL_POSITION_INT of system 1 stamped 0xFFFFFFFF during boot and take-off
    ended a lockstep daemon with struct.error in the SYSTEM_TIME grant."""

    def make(k: int) -> bytes | None:
        sysid = 1 + k % 3
        pos = ml.MAVLink_global_position_int_message(
            0xFFFFFFFF, -353632620, 1491652370, 600000, 500000, 10000, 0, 0, 9000
        )
        return pack(pos, sysid, 1, k)

    result, summary, spoofer, _ = fly_with_spoofer(tmp_path, make, signed=False, period_s=0.002)
    assert spoofer.sent > 100
    assert spoofer.received == 0  # no vehicle followed to the spoofer's address
    assert result["steps"] == STEPS
    assert result["violations"] == NO_VIOLATIONS
    assert 50 < result["plausibility"]["second_address"] <= spoofer.sent
    assert summary is not None and summary["fence_breaches"] == 0


@pytest.mark.timeout(200)
def test_a_lockstep_daemon_whose_simulator_runs_free_says_so_and_decides_nothing(tmp_path: Path):
    """Finding 4: after the ground station's silence the simulator released lockstep (running at
    --speedup); a --lockstep daemon (there: resumed) then flew its decisions against a
    free-running clock (20 turn violations, no late step). Here a ground station grants 5 s and
    goes silent, the simulator releases lockstep after 1 s, and a --lockstep daemon starts: it
    stops in one line, exit 2, before any decision step."""
    port = free_udp_port()
    sim_log, daemon_log = tmp_path / "sim.log", tmp_path / "daemon.log"
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", port))
    gcs.settimeout(60)
    sim = start_swarmplan(
        ["sim", "--scenario", "paper-2uav", "--seed", "2", "--lockstep", "--speedup", "20",
         "--lockstep-timeout", "1", "--gcs-port", str(port)],
        sim_log,
    )  # fmt: skip
    daemon = None
    try:
        _, vehicle = gcs.recvfrom(65535)  # the first vehicle to speak: grant it 5 s, then silence
        gcs.sendto(pack(ml.MAVLink_system_time_message(0, 5000), 255, 190), vehicle)
        gcs.close()
        released = lambda: "lockstep released" in sim_log.read_text(errors="replace")  # noqa: E731
        assert _wait_for(released, 60), sim_log.read_text(errors="replace")[-2000:]
        daemon = start_swarmplan(
            ["daemon", "--connect", f"udpin:127.0.0.1:{port}", "--scenario", "paper-2uav",
             "--seed", "2", "--steps", "30", "--lockstep", "--timeout", "30",
             "--out", str(tmp_path / "out"), "--json"],
            daemon_log,
            stdout_pipe=True,
        )  # fmt: skip
        stdout, _ = daemon.communicate(timeout=150)
    finally:
        gcs.close()
        if daemon is not None:
            stop(daemon)
        stop(sim)
    log = daemon_log.read_text(errors="replace")
    assert "Traceback" not in log, log[-3000:]
    assert daemon.returncode == 2, log[-3000:]
    assert "is not in lockstep" in log, log[-3000:]
    result = json.loads(stdout) if stdout.strip() else {"steps": 0}
    assert result["steps"] == 0  # not one decision against the free-running clock


def _wait_for(predicate: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.1)
    return False


@pytest.mark.timeout(200)
def test_spoofed_and_replayed_positions_from_the_vehicles_own_address_are_not_believed(
    tmp_path: Path,
):
    """Finding 7: without signing, spoofed and replayed vehicle frames were believed (results
    falsified: threat 11, turn 58, range 31 in one run). Here the spoofer sits on the path (the
    fault relay's socket of each vehicle, so its frames come from the vehicle's own address) and
    sends, as vehicles 1-3, positions inside a threat stamped just after their latest time,
    replays of their first positions, and a clock near 0xFFFFFFFF: none is believed, each is
    counted by its rule, and the mission's account stays what the simulator itself measured."""
    scenario = load_scenario(SCENARIO)
    daemon = MissionDaemon(
        scenario,
        DaemonOptions(
            connect=["udpin:127.0.0.1:0"], seed=5, steps=STEPS, lockstep=True,
            discovery_timeout_s=60, rtl_watch_s=0.0,
        ),
    )  # fmt: skip
    link = daemon.connect()
    relay = FaultRelay(link.endpoints[0].port, scenario.uav_count, FaultProfile(), seed=5)
    relay.start()
    threat = scenario.threats[0]
    lat, lon = local_km_to_geodetic([threat.x_km], [threat.y_km], scenario.origin)
    inside = (round(float(lat[0]) * 1e7), round(float(lon[0]) * 1e7))
    first_seen: dict[int, tuple[int, int, int]] = {}

    def spoof(k: int) -> None:
        sysid = 1 + k % 3
        v = link.vehicle(sysid)
        if v is None or not v.has_position:
            return
        here = (v.time_boot_ms, round(v.lat_deg * 1e7), round(v.lon_deg * 1e7))
        first_seen.setdefault(sysid, here)
        kind = k // 3 % 3
        if kind == 0:  # teleported into the threat at the instant of its latest report
            when, (la, lo) = v.time_boot_ms, inside
        elif kind == 1:  # a replay of its first report
            when, la, lo = first_seen[sysid]
        else:  # its clock near the end of uint32: what a lockstep grant would echo
            when, la, lo = 0xFFFFFFF0, here[1], here[2]
        pos = ml.MAVLink_global_position_int_message(when, la, lo, 500000, 500000, 0, 0, 0, 9000)
        relay.socks[sysid - 1].sendto(pack(pos, sysid, 1, k), relay.daemon_addr)

    stop_spoofing = threading.Event()

    def spoofer() -> None:
        k = 0
        while not stop_spoofing.wait(0.01):
            spoof(k)
            k += 1

    sim_log = tmp_path / "sim.log"
    sim = start_swarmplan(
        ["sim", "--scenario", SCENARIO, "--seed", "5", "--lockstep", "--speedup", "100",
         "--per-vehicle-ports", str(relay.base_port), "--quiet"],
        sim_log,
    )  # fmt: skip
    thread = threading.Thread(target=spoofer, daemon=True)
    thread.start()
    try:
        result = daemon.fly().result
    finally:
        stop_spoofing.set()
        thread.join(5)
        stop(sim)
        relay.stop()
    summary = last_json(sim_log)
    trust = result["plausibility"]
    assert result["steps"] == STEPS and result["lost_uavs"] == []
    assert result["violations"] == NO_VIOLATIONS
    assert trust["too_fast"] > 20 and trust["stale_positions"] > 20, trust
    assert trust["time_jump"] > 20 and trust["clock_rebases"] == 0, trust
    mission = result["track_audit"]["phases"]["mission"]
    assert mission["threat_entries"] == 0
    assert summary is not None and summary["safety"]["by_mode"]["guided"]["threat_entries"] == 0


@pytest.mark.timeout(200)
def test_a_lockstep_simulator_paused_longer_than_lost_after_loses_no_vehicle(tmp_path: Path):
    """Under load (the project's CI on 2 cores) the whole simulator can stall for seconds. In
    lockstep its time stands still meanwhile, yet the daemon counted wall-clock silence: every
    vehicle was marked lost at once (seen: all 10 'silent' at step 6), and the mission flew on
    without them. Here the simulator is SIGSTOPped for 4 s (lost_after_s 3) mid-mission: no
    vehicle is lost and every UAV flies every step."""
    scenario = load_scenario(SCENARIO)
    sim_holder: list = []

    def pause_at_step(status) -> None:
        if status.step == 3:

            def pause() -> None:
                os.kill(sim_holder[0].pid, signal.SIGSTOP)
                time.sleep(4.0)
                os.kill(sim_holder[0].pid, signal.SIGCONT)

            threading.Thread(target=pause, daemon=True).start()

    daemon = MissionDaemon(
        scenario,
        DaemonOptions(
            connect=["udpin:127.0.0.1:0"], seed=6, steps=STEPS, lockstep=True,
            lost_after_s=3.0, discovery_timeout_s=60, rtl_watch_s=0.0, on_step=pause_at_step,
        ),
    )  # fmt: skip
    link = daemon.connect()
    sim = start_swarmplan(
        ["sim", "--scenario", SCENARIO, "--seed", "6", "--lockstep", "--speedup", "100",
         "--gcs-port", str(link.endpoints[0].port), "--quiet"],
        tmp_path / "sim.log",
    )  # fmt: skip
    sim_holder.append(sim)
    try:
        result = daemon.fly().result
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(sim.pid, signal.SIGCONT)
        stop(sim)
    assert result["steps"] == STEPS
    assert result["lost_uavs"] == [], result["link_events"]
    assert all(len(u["track_km"]) == STEPS + 1 for u in result["uavs"])
