"""No address taken before discovery (issue 31, findings 3 and 6): a real simulator and a real
daemon over loopback UDP, and a stranger's socket that talks to the daemon before the vehicles
are first heard. Only an autopilot's HEARTBEAT that carries a vehicle type binds a system id to
an address; a second address claiming a bound system id is refused, counted once and said in
one line; nothing is sent to it; and every frame dropped before discovery is counted."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import contextlib  # noqa: E402
import json  # noqa: E402
import signal  # noqa: E402
import socket  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from loopback import free_udp_port, start_swarmplan, stop  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402
from reliability_harness import KEY_HEX, last_json  # noqa: E402
from test_link_trust import NO_VIOLATIONS, Spoofer, pack  # noqa: E402

from mavlink_bridge.mission.daemon import DaemonOptions, MissionDaemon  # noqa: E402
from mavlink_bridge.vehicles.swarm_link import SwarmLink  # noqa: E402
from mavlink_bridge.vehicles.telemetry_plausibility import PlausibilityFilter, PlausibilityLimits  # noqa: E402
from mavlink_wire.signing import sign_outgoing  # noqa: E402
from planner.scenario import load_scenario  # noqa: E402

SCENARIO = "paper-10uav"
KEY = bytes.fromhex(KEY_HEX)
CAMERA = ml.MAV_COMP_ID_CAMERA
STEPS = 4
FIXED_WING, ARDUPILOT, GCS, INVALID = (
    ml.MAV_TYPE_FIXED_WING, ml.MAV_AUTOPILOT_ARDUPILOTMEGA, ml.MAV_TYPE_GCS,
    ml.MAV_AUTOPILOT_INVALID,
)  # fmt: skip
#: GLOBAL_POSITION_INT stamped with the end of the vehicle clock, near the scenario's origin
FAR_FUTURE = ml.MAVLink_global_position_int_message(
    0xFFFFFFFF, -353632620, 1491652370, 600000, 500000, 10000, 0, 0, 9000
)


def _heartbeat(kind: int, autopilot: int, version: int = 3) -> ml.MAVLink_heartbeat_message:
    return ml.MAVLink_heartbeat_message(kind, autopilot, 0, 0, ml.MAV_STATE_STANDBY, version)


#: What a stranger sends before the vehicles are heard, as each vehicle's system id and
#: component 1: nothing here is a vehicle's HEARTBEAT, so none of it may bind an address
BEFORE_DISCOVERY = [
    _heartbeat(GCS, INVALID),  # a ground station
    _heartbeat(FIXED_WING, INVALID),  # a vehicle type, but no autopilot (once enough to bind)
    _heartbeat(200, ARDUPILOT),  # no vehicle type (a fuzzed one; once enough to bind)
    _heartbeat(FIXED_WING, ARDUPILOT, version=0),  # not the protocol's version byte
    ml.MAVLink_command_ack_message(ml.MAV_CMD_COMPONENT_ARM_DISARM, ml.MAV_RESULT_ACCEPTED),
    FAR_FUTURE,
]
#: What it adds once the vehicles are bound: a vehicle's HEARTBEAT claiming their system ids
AFTER_DISCOVERY = [*BEFORE_DISCOVERY, _heartbeat(FIXED_WING, ARDUPILOT)]


def _wait_for_line(log: Path, text: str, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if text in log.read_text(errors="replace"):
            return True
        time.sleep(0.05)
    return False


@pytest.mark.timeout(240)
@pytest.mark.parametrize("signed", [False, True], ids=["unsigned", "signed"])
def test_a_stranger_heard_before_the_vehicles_takes_no_address(tmp_path: Path, signed: bool):
    """Finding 3: without signing, a fuzzer started 1 s after launch was taken as vehicles 2,
    3 and 10, got 29 COMMAND_LONG and 15 lockstep grants meant for them, and the mission
    aborted before take-off. Here a stranger sends, as every vehicle, HEARTBEATs that are not a
    vehicle's, COMMAND_ACKs and positions stamped 0xFFFFFFFF from before the daemon listens;
    the simulator starts only once the daemon listens; after discovery the stranger also sends
    a vehicle's HEARTBEAT claiming each system id, also while the whole simulator is paused
    longer than --lost-after. The daemon binds the simulator's vehicles,
    flies its steps, sends the stranger nothing, and counts and says the refusals. Signed, the
    signature check refuses all of it first (counted there; no second address to refuse)."""
    port = free_udp_port()
    sim_log, daemon_log, out = tmp_path / "sim.log", tmp_path / "daemon.log", tmp_path / "out"
    key_file = tmp_path / "mission.key"
    key_file.write_text(KEY_HEX + "\n")
    signing = ["--signing-key-file", str(key_file)] if signed else []
    n = load_scenario(SCENARIO).uav_count
    discovered = threading.Event()

    def make(k: int) -> bytes:
        frames = AFTER_DISCOVERY if discovered.is_set() else BEFORE_DISCOVERY
        sysid = 1 + k % n
        return pack(frames[k // n % len(frames)], sysid, 1, k)

    spoofer = Spoofer(port, make, period_s=0.002)
    spoofer.start()
    daemon = start_swarmplan(
        ["daemon", "--connect", f"udpin:127.0.0.1:{port}", "--scenario", SCENARIO, "--seed", "3",
         "--steps", str(STEPS), "--lockstep", "--timeout", "60", "--out", str(out), "--no-view",
         *signing],
        daemon_log,
    )  # fmt: skip
    sim = None
    try:
        assert _wait_for_line(daemon_log, "listening on", 60), daemon_log.read_text()[-2000:]
        time.sleep(1.0)  # the stranger alone on the daemon's port, as in the audit
        sim = start_swarmplan(
            ["sim", "--scenario", SCENARIO, "--seed", "3", "--lockstep", "--speedup", "100",
             "--gcs-port", str(port), "--quiet", *signing],
            sim_log,
        )  # fmt: skip
        assert _wait_for_line(daemon_log, "vehicles heard;", 60), daemon_log.read_text()[-2000:]
        discovered.set()
        # the whole simulator paused longer than --lost-after (a loaded machine): every bound
        # address silent while the stranger claims the vehicles; no vehicle moves to it
        assert _wait_for_line(daemon_log, "airborne, GUIDED", 120), daemon_log.read_text()[-2000:]
        os.kill(sim.pid, signal.SIGSTOP)
        time.sleep(4.5)
        os.kill(sim.pid, signal.SIGCONT)
        daemon.wait(180)
    finally:
        spoofer.stop()
        stop(daemon)
        if sim is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(sim.pid, signal.SIGCONT)
            stop(sim)
    log = daemon_log.read_text(errors="replace")
    assert "Traceback" not in log, log[-3000:]
    assert daemon.returncode == 0, log[-3000:]
    result = json.loads((out / "result.json").read_text())
    assert result["steps"] == STEPS and result["lost_uavs"] == []
    assert result["violations"] == NO_VIOLATIONS
    summary = last_json(sim_log)
    assert summary is not None and summary["fence_breaches"] == 0
    assert spoofer.sent > 1000
    assert spoofer.received == 0, spoofer.received_types  # nothing meant for a vehicle
    trust = result["plausibility"]
    said = [line for line in log.splitlines() if ": refused 127.0.0.1:" in line]
    if signed:  # nothing unsigned reaches the binding: refused and counted by the signature check
        assert result["signing"]["unsigned_refused"] > 1000, result["signing"]
        assert trust["address_conflicts"] == trust["second_address"] == 0 and not said, trust
        return
    assert trust["unbound"] > 0, trust  # the stranger's frames before discovery, each counted
    assert trust["second_address"] > 0, trust
    # one address refused per system id it claims, counted once and said once
    assert trust["address_conflicts"] == n, trust
    assert len(said) == n, said
    assert trust["address_moves"] == 0, trust


def _dropped(counts: dict[str, int]) -> int:
    """Frames the plausibility filter dropped (its counters but the accepted events)."""
    return sum(v for k, v in counts.items() if k not in ("address_moves", "clock_rebases"))


@pytest.mark.timeout(200)
def test_every_spoofed_clock_before_discovery_is_counted(tmp_path: Path):
    """Finding 6: GLOBAL_POSITION_INT with time_boot_ms 0xFFFFFFFF sent 0.6 and 1.0 s after the
    start was dropped but not counted (1.5 s after, once the vehicles were heard, it was). Here
    the daemon listens, 20 such frames as vehicles 1 and 2 arrive before any vehicle, and every
    one is counted; the mission then flies with the simulator."""
    scenario = load_scenario("paper-2uav")
    daemon = MissionDaemon(
        scenario,
        DaemonOptions(
            connect=["udpin:127.0.0.1:0"], seed=2, steps=STEPS, lockstep=True,
            discovery_timeout_s=60, rtl_watch_s=0.0,
        ),
    )  # fmt: skip
    link = daemon.connect()
    port = link.endpoints[0].port
    spoofs = 20
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as stranger:
        for k in range(spoofs):
            stranger.sendto(pack(FAR_FUTURE, 1 + k % 2, 1, k), ("127.0.0.1", port))
        deadline = time.monotonic() + 10
        while link.messages_received < spoofs and time.monotonic() < deadline:
            link.pump(0.1)
    assert link.messages_received == spoofs and not link.vehicles
    assert _dropped(link.plausibility.counts.as_dict()) == spoofs  # every one counted
    sim = start_swarmplan(
        ["sim", "--scenario", "paper-2uav", "--seed", "2", "--lockstep", "--speedup", "100",
         "--gcs-port", str(port), "--quiet"],
        tmp_path / "sim.log",
    )  # fmt: skip
    try:
        result = daemon.fly().result
    finally:
        stop(sim)
    assert result["steps"] == STEPS and result["violations"] == NO_VIOLATIONS
    assert result["plausibility"]["unbound"] >= spoofs


class _Sender:
    """A UDP socket sending as (system 1, component 1) to ``port``: a vehicle, or a stranger."""

    def __init__(self, port: int, key: bytes | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(2.0)
        self.address = self.sock.getsockname()
        self.target = ("127.0.0.1", port)
        self.mav = ml.MAVLink(None, 1, 1)
        if key is not None:
            sign_outgoing(self.mav, key, 1)

    def send(self, *msgs: ml.MAVLink_message) -> None:
        for msg in msgs:
            self.sock.sendto(bytes(msg.pack(self.mav)), self.target)

    def heard_heartbeat(self) -> bool:
        """A HEARTBEAT from the daemon arrived here within 2 s."""
        try:
            data = self.sock.recv(65535)
        except TimeoutError:
            return False
        return any(m.get_type() == "HEARTBEAT" for m in ml.MAVLink(None).parse_buffer(data) or ())


def _pump(link: SwarmLink, seconds: float) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        link.pump(0.05)


@pytest.mark.timeout(60)
def test_a_vehicle_moves_only_by_its_own_heartbeat_after_its_address_fell_silent():
    """The rule for addresses that really move (a rebooted vehicle on a new socket): the bound
    address silent for ``move_after_s`` and a vehicle HEARTBEAT of the same type from the new
    one. A stranger's ACKs, positions, a ground station's or another vehicle type's HEARTBEAT
    in that silence move nothing (before: any 3 frames did)."""
    limits = PlausibilityLimits(move_after_s=1.0)
    link = SwarmLink.open(["udpin:127.0.0.1:0"], plausibility=PlausibilityFilter(limits))
    port = link.endpoints[0].port
    vehicle, stranger, rebooted = _Sender(port), _Sender(port), _Sender(port)
    try:
        vehicle.send(_heartbeat(FIXED_WING, ARDUPILOT))
        assert link.pump_until(lambda: link.vehicle(1) is not None, 5.0)
        assert link.vehicle(1).link.address == vehicle.address
        ack = ml.MAVLink_command_ack_message(ml.MAV_CMD_DO_REPOSITION, ml.MAV_RESULT_ACCEPTED)
        quad = _heartbeat(ml.MAV_TYPE_QUADROTOR, ARDUPILOT)
        stranger.send(ack, FAR_FUTURE)  # while the vehicle is alive: refused
        _pump(link, 1.3)  # the vehicle falls silent for longer than move_after_s
        for _ in range(5):
            stranger.send(ack, FAR_FUTURE, _heartbeat(GCS, INVALID), quad)
        _pump(link, 0.3)
        assert link.vehicle(1).link.address == vehicle.address  # nothing there moved it
        counts = link.plausibility.counts
        assert counts.address_moves == 0 and counts.address_conflicts == 1
        rebooted.send(_heartbeat(FIXED_WING, ARDUPILOT))  # the vehicle back on a new socket
        _pump(link, 0.3)
        assert link.vehicle(1).link.address == rebooted.address
        assert counts.address_moves == 1
        link.send_heartbeat()
        assert rebooted.heard_heartbeat()  # the daemon's frames follow the vehicle
    finally:
        link.close()
        for s in (vehicle, stranger, rebooted):
            s.sock.close()


@pytest.mark.timeout(60)
def test_with_signing_only_a_signed_heartbeat_binds():
    """Signing on: a stranger's unsigned vehicle HEARTBEATs, sent before the vehicle's own,
    bind nothing (refused and counted by the signature check); the vehicle's signed HEARTBEAT
    binds it."""
    link = SwarmLink.open(["udpin:127.0.0.1:0"], signing_key=KEY)
    port = link.endpoints[0].port
    stranger, vehicle = _Sender(port), _Sender(port, key=KEY)
    try:
        for _ in range(5):
            stranger.send(_heartbeat(FIXED_WING, ARDUPILOT))
        _pump(link, 0.3)
        assert not link.vehicles and link.signature_check.unsigned_refused == 5
        vehicle.send(_heartbeat(FIXED_WING, ARDUPILOT))
        assert link.pump_until(lambda: link.vehicle(1) is not None, 5.0)
        assert link.vehicle(1).link.address == vehicle.address
        stranger.send(_heartbeat(FIXED_WING, ARDUPILOT))
        _pump(link, 0.3)
        assert link.vehicle(1).link.address == vehicle.address
    finally:
        link.close()
        stranger.sock.close()
        vehicle.sock.close()


@pytest.mark.timeout(60)
def test_a_camera_claimed_by_a_stranger_is_taken_back_through_its_autopilot():
    """A stranger's camera HEARTBEAT as (1, 100), heard before the vehicle's own camera, bound
    the camera to the stranger (engagement commands went there; before, the real camera's
    frames were then refused). Now the camera's frames through its autopilot's address take it
    back, and commands to it go there."""
    link = SwarmLink.open(["udpin:127.0.0.1:0"])
    port = link.endpoints[0].port
    vehicle, stranger = _Sender(port), _Sender(port)
    camera_of = {s: ml.MAVLink(None, 1, CAMERA) for s in (vehicle, stranger)}
    camera_beat = _heartbeat(ml.MAV_TYPE_CAMERA, INVALID)
    try:
        vehicle.send(_heartbeat(FIXED_WING, ARDUPILOT))
        assert link.pump_until(lambda: link.vehicle(1) is not None, 5.0)
        stranger.sock.sendto(bytes(camera_beat.pack(camera_of[stranger])), stranger.target)
        assert link.pump_until(lambda: CAMERA in link.vehicle(1).component_links, 5.0)
        vehicle.sock.sendto(bytes(camera_beat.pack(camera_of[vehicle])), vehicle.target)
        _pump(link, 0.3)
        assert link.vehicle(1).link_for(CAMERA).address == vehicle.address
        for _ in range(3):  # the stranger's camera HEARTBEATs go on: refused now
            stranger.sock.sendto(bytes(camera_beat.pack(camera_of[stranger])), stranger.target)
        _pump(link, 0.3)
        assert link.vehicle(1).link_for(CAMERA).address == vehicle.address
        assert link.plausibility.counts.address_conflicts == 1
    finally:
        link.close()
        vehicle.sock.close()
        stranger.sock.close()
