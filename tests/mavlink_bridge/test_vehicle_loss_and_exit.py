"""One vehicle's failure stays one vehicle's, and every way out of a mission sends RTL to the
airborne vehicles only and writes what was flown. Real processes on loopback: the simulator
(``swarmplan sim --per-vehicle-ports``) behind relays the test watches (every heartbeat of every
vehicle) and breaks (a TCP connection dropped, a vehicle force-disarmed by another ground
station), and the daemon in-process or as ``swarmplan daemon``."""

from __future__ import annotations

import json
import re
import signal
import time
from pathlib import Path

import pytest
from loopback import free_port_block, free_udp_port, start_swarmplan, stop
from vehicle_relays import DroppableTcpBridge, WatchingRelay

from mavlink_bridge.mission.daemon import DaemonOptions, MissionDaemon
from mavlink_wire.protocol import PLANE_MODE_RTL, mavlink
from planner.scenario import load_scenario

STEPS = 14


def start_sim(base: int, log: Path, scenario: str = "paper-2uav", lockstep: bool = True):
    pace = ["--lockstep", "--speedup", "50"] if lockstep else ["--speedup", "50"]
    return start_swarmplan(
        ["sim", "--scenario", scenario, "--seed", "1", *pace, "--per-vehicle-ports", str(base),
         "--quiet"],
        log,
    )  # fmt: skip


def relays_for(daemon_port: int, base: int, n: int) -> list[WatchingRelay]:
    relays = [WatchingRelay(daemon_port, base + i, i + 1) for i in range(n)]
    for r in relays:
        r.start()
    return relays


def wait_for(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return predicate()


def sent_modes(tlog: Path) -> list[int]:
    """Every mode the daemon (system 255) commanded in ``tlog`` (DO_SET_MODE param2)."""
    data, k, modes = tlog.read_bytes(), 0, []
    parser = mavlink.MAVLink(None)
    while k + 10 <= len(data):
        at = k + 8
        length, flags = data[at + 1], data[at + 2]
        size = 12 + length + (13 if flags & 1 else 0)
        for msg in parser.parse_buffer(data[at : at + size]) or ():
            ours = msg.get_srcSystem() == 255 and msg.get_type() == "COMMAND_LONG"
            if ours and msg.command == mavlink.MAV_CMD_DO_SET_MODE:
                modes.append(int(msg.param2))
        k = at + size
    return modes


@pytest.mark.timeout(120)
def test_sigterm_mid_mission_sends_rtl_to_every_airborne_vehicle_and_writes_the_result(tmp_path):
    """`kill` (SIGTERM) of `swarmplan daemon` at step 4 of 14: every vehicle's own heartbeat
    turns to RTL, the daemon says so, exits 143, and result.json (the steps flown), the figures
    and the tlog are in --out."""
    port, base = free_udp_port(), free_port_block(2)
    relays = relays_for(port, base, 2)
    sim = start_sim(base, tmp_path / "sim.log")
    log = tmp_path / "daemon.log"
    daemon = start_swarmplan(
        ["daemon", "--connect", f"udpin:127.0.0.1:{port}", "--scenario", "paper-2uav", "--seed",
         "1", "--steps", str(STEPS), "--lockstep", "--timeout", "20", "--out", str(tmp_path)],
        log,
    )  # fmt: skip
    try:
        assert wait_for(lambda: re.search(r"step +4/", log.read_text()), 60), log.read_text()
        assert all(r.watch.mode == 15 for r in relays)  # GUIDED, flying the mission
        daemon.send_signal(signal.SIGTERM)
        status = daemon.wait(30)
        assert wait_for(lambda: all(r.watch.mode == PLANE_MODE_RTL for r in relays), 10), [
            r.watch.modes for r in relays
        ]
    finally:
        stop(daemon)
        stop(sim)
        for r in relays:
            r.stop()
    text = log.read_text()
    assert status == 143, text[-2000:]
    assert "RTL sent to vehicles 1, 2" in text and "interrupted (SIGTERM)" in text
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["ended"] == "interrupted (SIGTERM)" and result["ended_in_phase"] == "decisions"
    assert result["rtl_sent_to"] == [1, 2]
    assert 4 <= result["steps"] < STEPS
    for name in ("paths.png", "coverage.png", "mission.tlog"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert sent_modes(tmp_path / "mission.tlog")[-1] == PLANE_MODE_RTL


@pytest.mark.timeout(90)
def test_grounded_disarmed_vehicles_never_get_rtl(tmp_path):
    """`--expect 3` with two simulated planes on the ground: discovery fails (one line, exit 2),
    and neither grounded, disarmed plane is sent RTL (their heartbeats never say RTL); the
    result says why (on the ground, disarmed)."""
    port, base = free_udp_port(), free_port_block(2)
    relays = relays_for(port, base, 2)
    sim = start_sim(base, tmp_path / "sim.log", lockstep=False)
    log = tmp_path / "daemon.log"
    daemon = start_swarmplan(
        ["daemon", "--connect", f"udpin:127.0.0.1:{port}", "--scenario", "paper-2uav", "--expect",
         "3", "--timeout", "3", "--out", str(tmp_path)],
        log,
    )  # fmt: skip
    try:
        status = daemon.wait(40)
        time.sleep(1.0)  # a mode change would show in the next heartbeats
    finally:
        stop(daemon)
        stop(sim)
        for r in relays:
            r.stop()
    text = log.read_text()
    assert status == 2, text[-2000:]
    assert "system id 3 did not appear" in text.strip().splitlines()[-1]
    assert all(r.watch.heartbeats > 0 and PLANE_MODE_RTL not in r.watch.modes for r in relays)
    assert PLANE_MODE_RTL not in sent_modes(tmp_path / "mission.tlog")
    result = json.loads((tmp_path / "result.json").read_text())
    assert result["rtl_sent_to"] == []
    grounded = "on the ground, disarmed"
    assert result["rtl_not_sent"] == {"1": grounded, "2": grounded}
    assert result["ended"].startswith("error: vehicle with system id 3 did not appear")


def fly_in_process(connect: list[str], tmp_path: Path, on_step) -> MissionDaemon:
    daemon = MissionDaemon(
        load_scenario("paper-2uav"),
        DaemonOptions(
            connect=connect,
            seed=1,
            steps=STEPS,
            lockstep=True,
            lost_after_s=1.0,
            discovery_timeout_s=20,
            tlog_path=tmp_path / "m.tlog",
            on_step=on_step,
        ),
    )
    daemon.fly()
    return daemon


@pytest.mark.timeout(120)
def test_a_vehicle_disarmed_mid_mission_is_lost_and_the_other_finishes(tmp_path):
    """Another ground station force-disarms vehicle 2 at step 4 (it drops to the ground): the
    daemon marks it lost ("disarmed"), flies vehicle 1 to the end, and at the end sends RTL to
    vehicle 1 only."""
    port, base = free_udp_port(), free_port_block(2)
    relays = relays_for(port, base, 2)
    sim = start_sim(base, tmp_path / "sim.log")

    def on_step(status) -> None:
        if status.step == 4:
            relays[1].force_disarm()

    try:
        daemon = fly_in_process([f"udpin:127.0.0.1:{port}"], tmp_path, on_step)
        wait_for(lambda: relays[0].watch.mode == PLANE_MODE_RTL, 10)  # heartbeats: 1 Hz
        time.sleep(1.5)  # vehicle 2's next heartbeats would show an RTL too
    finally:
        stop(sim)
        for r in relays:
            r.stop()
    result = daemon.report.result
    assert result["ended"] == "completed" and result["steps"] == STEPS
    assert result["lost_uavs"] == [1]
    lost = [e for e in result["link_events"] if e["event"] == "lost"]
    assert lost[0]["uav"] == 1 and lost[0]["reason"] == "disarmed"
    assert result["rtl_sent_to"] == [1]
    assert result["rtl_not_sent"] == {"2": "on the ground, disarmed"}
    assert PLANE_MODE_RTL in relays[0].watch.modes
    assert PLANE_MODE_RTL not in relays[1].watch.modes and relays[1].watch.armed is False


@pytest.mark.timeout(120)
def test_a_closed_tcp_link_loses_one_vehicle_which_rejoins_when_it_is_back(tmp_path):
    """One TCP connection per vehicle (SITL style). Vehicle 2's server closes the connection at
    step 3 and refuses new ones until step 7: the daemon marks it lost (link closed) and flies
    on with vehicle 1; it reconnects (with backoff) when the server is back, vehicle 2 rejoins,
    and both finish and get RTL."""
    base = free_port_block(2)
    bridges = [DroppableTcpBridge(base + i) for i in range(2)]
    for b in bridges:
        b.start()
    sim = start_sim(base, tmp_path / "sim.log")

    def on_step(status) -> None:
        if status.step == 3:
            bridges[1].drop()
        if status.step == 7:
            bridges[1].restore()

    try:
        daemon = fly_in_process([f"tcp:127.0.0.1:{b.port}" for b in bridges], tmp_path, on_step)
    finally:
        stop(sim)
        for b in bridges:
            b.stop()
    result = daemon.report.result
    assert result["ended"] == "completed" and result["steps"] == STEPS
    events = [(e["uav"], e["event"]) for e in result["link_events"]]
    assert events[:2] == [(1, "lost"), (1, "rejoined")], result["link_events"]
    assert "connection closed" in result["link_events"][0]["reason"]
    assert bridges[1].connections >= 2  # it connected again
    assert result["rtl_sent_to"] == [1, 2]


@pytest.mark.timeout(120)
def test_an_error_mid_mission_sends_rtl_to_every_airborne_vehicle_and_keeps_the_result(tmp_path):
    """A fault inside the decision loop (here a step listener that raises at step 3, as a broken
    live view would): the error goes up to the caller, but first both flying vehicles get RTL
    (their own heartbeats say so) and the result of the steps flown is kept with how it ended."""
    port, base = free_udp_port(), free_port_block(2)
    relays = relays_for(port, base, 2)
    sim = start_sim(base, tmp_path / "sim.log")

    def on_step(status) -> None:
        if status.step == 3:
            raise RuntimeError("listener broke")

    daemon = None
    try:
        with pytest.raises(RuntimeError, match="listener broke"):
            daemon = MissionDaemon(
                load_scenario("paper-2uav"),
                DaemonOptions(
                    connect=[f"udpin:127.0.0.1:{port}"], seed=1, steps=STEPS, lockstep=True,
                    discovery_timeout_s=20, tlog_path=tmp_path / "m.tlog", on_step=on_step,
                ),
            )  # fmt: skip
            daemon.fly()
        assert wait_for(lambda: all(r.watch.mode == PLANE_MODE_RTL for r in relays), 10), [
            r.watch.modes for r in relays
        ]
    finally:
        stop(sim)
        for r in relays:
            r.stop()
    assert daemon is not None and daemon.report is not None
    result = daemon.report.result
    assert result["ended"] == "error: RuntimeError: listener broke"
    assert result["ended_in_phase"] == "decisions" and result["steps"] == 3
    assert result["rtl_sent_to"] == [1, 2]
    assert sent_modes(tmp_path / "m.tlog")[-1] == PLANE_MODE_RTL
