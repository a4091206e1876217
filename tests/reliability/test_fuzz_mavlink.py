"""Fuzzing the MAVLink intake of the simulator and the daemon with seeded random, mutated and
hostile well-formed frames: 100,000 datagrams over the three tests. Nothing may escape as an
exception, and afterwards every vehicle still answers and flies, and the daemon's consumers of
what it heard (positions, looks, starts) still work."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import math  # noqa: E402
import socket  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from mavlink_fuzz import Fuzzer, classes_named  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402

from mavlink_bridge.mission.daemon import DaemonOptions, MissionDaemon  # noqa: E402
from mavlink_bridge.mission.loop_state import course_heading  # noqa: E402
from mavlink_bridge.vehicles.sensor_looks import look_report  # noqa: E402
from mavlink_bridge.vehicles.swarm_link import SwarmLink  # noqa: E402
from mavlink_wire.links import UdpInEndpoint  # noqa: E402
from planner.scenario import load_scenario  # noqa: E402
from sim_gateway.message_handlers import HANDLERS  # noqa: E402
from sim_gateway.simulator import SimOptions, Simulator  # noqa: E402

SIM_DIRECT = 50_000
DAEMON_DIRECT = 40_000
SIM_UDP = 10_000
#: What a daemon hears from vehicles (and could be lied to with).
DAEMON_MESSAGES = [
    "HEARTBEAT", "GLOBAL_POSITION_INT", "HOME_POSITION", "STATUSTEXT", "COMMAND_ACK",
    "CAMERA_IMAGE_CAPTURED", "MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK",
    "SYS_STATUS", "ATTITUDE", "SYSTEM_TIME", "PARAM_VALUE",
]  # fmt: skip
GCS = (255, 190)


def _legit(msg: ml.MAVLink_message, seq: int) -> bytes:
    # another ground-station identity than the fuzzer's: its random sequence numbers would make
    # commands of the same sender look overtaken (reordered) for REORDER_WINDOW_S
    mav = ml.MAVLink(None, 254, 190)
    mav.seq = seq % 256
    return bytes(msg.pack(mav))


def _assert_sane(sim: Simulator) -> None:
    f = sim.fleet
    for name in ("x_m", "y_m", "alt_m", "airspeed_mps"):
        assert np.isfinite(getattr(f, name)).all(), name


def _fly_again(sim: Simulator, seq0: int) -> None:
    """Legit commands after the storm: every vehicle takes them and moves."""
    origin = sim.origin
    for v in sim.vehicles:
        s = seq0 + 10 * v.sysid
        for k, msg in enumerate(
            (
                ml.MAVLink_param_set_message(v.sysid, 1, b"AIRSPEED_CRUISE", 100.0, 9),
                ml.MAVLink_command_long_message(v.sysid, 1, 176, 0, 1, 13, 0, 0, 0, 0, 0),
                ml.MAVLink_command_long_message(v.sysid, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0),
                ml.MAVLink_command_int_message(
                    v.sysid, 1, ml.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 192, 0, 0, -1, 1, 0, 0,
                    round((origin.lat_deg + 0.2) * 1e7), round((origin.lon_deg + 0.2) * 1e7), 400,
                ),
            )
        ):  # fmt: skip
            sim.handle_datagram(_legit(msg, s + k))
    before = np.stack([sim.fleet.x_m.copy(), sim.fleet.y_m.copy()])
    for _ in range(300):
        sim.tick()
    after = np.stack([sim.fleet.x_m, sim.fleet.y_m])
    _assert_sane(sim)
    moved = np.hypot(*(after - before))
    assert (moved > 1000).all(), moved  # 30 s simulated: every vehicle flew > 1 km
    assert all(v.armed and v.mode == 15 for v in sim.vehicles)
    assert sim.fleet.airborne.all()


@pytest.mark.timeout(120)
def test_fuzzing_the_simulator_parse_path(capsys):
    sim = Simulator(load_scenario("paper-2uav"), SimOptions(gcs_port=9, airborne=True, boot_s=0.0))
    fuzzer = Fuzzer(11, classes_named(HANDLERS), [GCS, (1, 1), (7, 100), (0, 0)])
    fuzzer.senders += [(255, 190)] * 4
    started = time.perf_counter()
    try:
        for k in range(SIM_DIRECT):
            sim.handle_datagram(fuzzer.datagram())
            if k % 50 == 0:
                sim.tick()
            if k % 500 == 0:
                sim.telemetry_frame(time.monotonic())
                _assert_sane(sim)
        elapsed = time.perf_counter() - started
        s = sim.stats
        assert s.datagrams == SIM_DIRECT
        assert s.bad_datagrams > SIM_DIRECT * 0.4 and s.frames > SIM_DIRECT * 0.3
        assert s.rejected_commands > 0 and sum(s.by_type.values()) > 10_000
        with capsys.disabled():
            print(f"\nsim fuzz: {SIM_DIRECT} datagrams in {elapsed:.1f} s "
                  f"({SIM_DIRECT / elapsed:,.0f}/s), {s.frames} well-formed frames handled, "
                  f"{s.bad_datagrams} bad datagrams, {s.rejected_commands} rejected")  # fmt: skip
        _fly_again(sim, 1000)
    finally:
        sim.close()


@pytest.mark.timeout(120)
def test_fuzzing_the_daemon_intake(capsys):
    scenario = load_scenario("paper-10uav")
    endpoint = UdpInEndpoint(spec="udpin:127.0.0.1:0", host="127.0.0.1", port=0).open()
    link = SwarmLink([endpoint])
    daemon = MissionDaemon(scenario, DaemonOptions(connect=[]))
    daemon.ctx.link = link
    beat = ml.MAVLink_heartbeat_message(ml.MAV_TYPE_FIXED_WING, 3, 0, 0, 3, 3)
    for sysid in range(1, 11):
        mav = ml.MAVLink(None, sysid, 1)
        for msg in endpoint.parse_datagram(bytes(beat.pack(mav))):
            link._dispatch(msg, endpoint, ("127.0.0.1", 40000 + sysid), time.monotonic())
    senders = [(s, c) for s in range(1, 11) for c in (1, 100)] + [(0, 0), (255, 190)]
    fuzzer = Fuzzer(12, classes_named(DAEMON_MESSAGES), senders)
    cfg = scenario.config
    started = time.perf_counter()
    try:
        for k in range(DAEMON_DIRECT):
            # the endpoint's own per-datagram intake (UdpInEndpoint.receive without the socket)
            for msg in endpoint.parse_datagram(fuzzer.datagram()):
                link._dispatch(msg, endpoint, ("127.0.0.1", 40001), time.monotonic())
            if k % 400 == 0:  # what the decision loop does with what it heard
                starts = daemon.loop.starts_from_telemetry()
                assert len(starts) == 10
                assert all(math.isfinite(s.x_km) and math.isfinite(s.y_km) for s in starts)
                for i in range(10):
                    v = daemon.vehicle(i)
                    xy = daemon.ctx.local_km(v.lat_deg, v.lon_deg)
                    assert np.isfinite(xy).all()
                    assert daemon.ctx.grid.inside(daemon.ctx.grid.cell_of(xy))
                    course_heading(v)
                    if v.latest_look >= 0:
                        report = look_report(
                            v.looks[v.latest_look], daemon.ctx.grid, scenario.origin,
                            cfg.detection_radius_km,
                        )  # fmt: skip
                        assert daemon.ctx.grid.inside(report.cells).all()
                        assert len(report.detected) == len(report.cells)
        elapsed = time.perf_counter() - started
        stats = endpoint.stats
        assert stats.bad_frames > 1000 and stats.frames > 10_000
        with capsys.disabled():
            print(f"\ndaemon fuzz: {DAEMON_DIRECT} datagrams in {elapsed:.1f} s "
                  f"({DAEMON_DIRECT / elapsed:,.0f}/s), {stats.frames} frames kept, "
                  f"{stats.bad_frames} bad, {stats.unknown_frames} unknown")  # fmt: skip
    finally:
        link.close()


@pytest.mark.timeout(120)
def test_fuzzing_a_running_simulator_over_udp(capsys):
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", 0))
    gcs.settimeout(0.1)
    sim = Simulator(
        load_scenario("paper-2uav"),
        SimOptions(gcs_port=gcs.getsockname()[1], airborne=True, boot_s=0.0, speedup=20.0),
    )
    stop = threading.Event()
    thread = threading.Thread(target=sim.run, kwargs={"stop": stop})
    thread.start()
    fuzzer = Fuzzer(13, classes_named(HANDLERS), [GCS, (3, 1), (0, 0)])
    targets = [("127.0.0.1", s.local_port) for s in sim.sockets]
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        started = time.perf_counter()
        for k in range(SIM_UDP):
            sender.sendto(fuzzer.datagram(), targets[k % len(targets)])
            if k % 200 == 199:
                time.sleep(0.01)  # let the simulator's loop keep up (its socket buffer is 1 MB)
        elapsed = time.perf_counter() - started
        deadline = time.monotonic() + 10
        while sim.stats.datagrams < SIM_UDP * 0.98 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert thread.is_alive()
        # every vehicle still answers a legit ground station
        mav = ml.MAVLink(None, *GCS)
        answered = set()
        deadline = time.monotonic() + 5
        while answered != {1, 2} and time.monotonic() < deadline:
            for sysid, target in zip((1, 2), targets, strict=True):
                msg = ml.MAVLink_command_long_message(sysid, 1, 512, 0, 1, 0, 0, 0, 0, 0, 0)
                gcs.sendto(bytes(msg.pack(mav)), target)
                mav.seq = (mav.seq + 1) % 256
            t_end = time.monotonic() + 0.3
            while time.monotonic() < t_end:
                try:
                    data = gcs.recv(65535)
                except TimeoutError:
                    continue
                for m in ml.MAVLink(None).parse_buffer(data) or ():
                    if m.get_type() == "COMMAND_ACK" and m.command == 512 and m.result == 0:
                        answered.add(m.get_srcSystem())
        assert answered == {1, 2}
        with capsys.disabled():
            print(f"\nsim UDP fuzz: {SIM_UDP} datagrams sent in {elapsed:.1f} s, "
                  f"{sim.stats.datagrams} received, {sim.stats.bad_datagrams} bad")  # fmt: skip
    finally:
        stop.set()
        thread.join(10)
        sender.close()
        gcs.close()
    _assert_sane(sim)
    _fly_again(sim, 2000)
    sim.close()
