"""MAVLink 2 signing: the simulator refuses and counts unsigned, wrongly signed and replayed
commands while signing is on (a spoofer on another port changes nothing), the two sides'
implementations agree, and keys come only from a file or the environment: the simulator makes
its key file when there is none, and a daemon flying unsigned says so as it starts."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import socket  # noqa: E402
import stat  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from loopback import env, free_udp_port, run_swarmplan  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402
from reliability_harness import KEY_HEX  # noqa: E402

from mavlink_wire import signing as bridge_signing  # noqa: E402
from planner.scenario import load_scenario  # noqa: E402
from sim_gateway.simulator import SimOptions, Simulator  # noqa: E402

KEY = bytes.fromhex(KEY_HEX)
OTHER_KEY = bytes(range(32))


def _encoder(sysid: int, key: bytes | None, link_id: int = 1) -> ml.MAVLink:
    mav = ml.MAVLink(None, sysid, 190)
    if key is not None:
        bridge_signing.sign_outgoing(mav, key, link_id)
    return mav


def _pack(mav: ml.MAVLink, msg: ml.MAVLink_message) -> bytes:
    frame = bytes(msg.pack(mav))
    mav.seq = (mav.seq + 1) % 256
    return frame


def _set_mode(mode: int) -> ml.MAVLink_message:
    return ml.MAVLink_set_mode_message(1, ml.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)


def _reposition(lat: float, lon: float) -> ml.MAVLink_message:
    return ml.MAVLink_command_int_message(
        1, 1, ml.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, ml.MAV_CMD_DO_REPOSITION, 0, 0,
        -1, 1, 0, 0, round(lat * 1e7), round(lon * 1e7), 500,
    )  # fmt: skip


class _SignedSim:
    """A signed simulator in a thread, a signed ground station and a spoofer on another port."""

    def __init__(self) -> None:
        self.gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.gcs.bind(("127.0.0.1", 0))
        self.gcs.settimeout(0.1)
        options = SimOptions(
            gcs_port=self.gcs.getsockname()[1], airborne=True, boot_s=0.0, speedup=10.0,
            signing_key=KEY,
        )  # fmt: skip
        self.sim = Simulator(load_scenario("paper-2uav"), options)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.sim.run, kwargs={"stop": self.stop})
        self.thread.start()
        self.vehicle_addr = ("127.0.0.1", self.sim.sockets[0].local_port)
        self.spoofer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.spoofer.bind(("127.0.0.1", 0))
        self.mav = _encoder(255, KEY)
        self.check = bridge_signing.SignatureCheck(KEY)  # the daemon's checker on the replies
        self.heard: list[ml.MAVLink_message] = []

    def receive(self, seconds: float) -> list[ml.MAVLink_message]:
        out, deadline = [], time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                data = self.gcs.recv(65535)
            except TimeoutError:
                continue
            for msg in ml.MAVLink(None).parse_buffer(data) or ():
                if self.check.accept_message(msg):
                    out.append(msg)
        self.heard += out
        return out

    def acks(self, seconds: float, command: int) -> list[ml.MAVLink_message]:
        heard = self.receive(seconds)
        return [m for m in heard if m.get_type() == "COMMAND_ACK" and m.command == command]

    def close(self) -> None:
        self.stop.set()
        self.thread.join(10)
        self.sim.close()
        self.gcs.close()
        self.spoofer.close()


@pytest.fixture
def signed() -> _SignedSim:
    running = _SignedSim()
    yield running
    running.close()


@pytest.mark.timeout(60)
def test_spoofed_unsigned_or_forged_commands_are_refused_and_counted(signed: _SignedSim):
    sim, vehicle = signed.sim, signed.sim.vehicles[0]
    assert signed.receive(0.5), "the vehicles' signed telemetry passes the daemon's check"
    assert signed.check.unsigned_refused == 0 and signed.check.bad_signatures == 0
    # the real ground station (signed) puts vehicle 1 in GUIDED
    signed.gcs.sendto(_pack(signed.mav, _set_mode(15)), signed.vehicle_addr)
    acks = signed.acks(1.0, ml.MAVLINK_MSG_ID_SET_MODE)
    assert acks and acks[0].result == ml.MAV_RESULT_ACCEPTED and vehicle.mode == 15
    target = (vehicle.guided.x_m, vehicle.guided.y_m)
    lat, lon = sim.origin.lat_deg + 0.3, sim.origin.lon_deg + 0.3
    # a stranger on another port: unsigned DO_REPOSITION and SET_MODE (RTL) as system 255 too
    unsigned = _encoder(255, None)
    forged = _encoder(255, OTHER_KEY)
    for mav in (unsigned, forged):
        for _ in range(5):
            signed.spoofer.sendto(_pack(mav, _reposition(lat, lon)), signed.vehicle_addr)
            signed.spoofer.sendto(_pack(mav, _set_mode(11)), signed.vehicle_addr)
    # a signed frame replayed later by the stranger (after the duplicate window)
    replayed = _pack(signed.mav, _set_mode(12))
    signed.gcs.sendto(replayed, signed.vehicle_addr)
    assert signed.acks(1.0, ml.MAVLINK_MSG_ID_SET_MODE)[0].result == 0 and vehicle.mode == 12
    signed.gcs.sendto(_pack(signed.mav, _set_mode(15)), signed.vehicle_addr)
    signed.receive(2.2)
    signed.spoofer.sendto(replayed, signed.vehicle_addr)
    signed.receive(0.5)
    check = sim.signature_check
    assert check.unsigned_refused >= 10
    assert check.bad_signatures >= 10
    assert check.replays >= 1
    assert vehicle.mode == 15  # neither RTL (spoofed) nor LOITER (replayed)
    assert (vehicle.guided.x_m, vehicle.guided.y_m) == target
    summary = sim.summary()
    assert summary["unsigned_refused"] == check.unsigned_refused
    # the spoofer got no answer at all: its frames never reached a handler
    signed.spoofer.settimeout(0.2)
    with pytest.raises(TimeoutError):
        signed.spoofer.recv(65535)


@pytest.mark.timeout(30)
def test_unsigned_radio_status_is_accepted_and_heartbeat_is_not(signed: _SignedSim):
    check = signed.sim.signature_check
    unsigned = _encoder(51, None)
    radio = ml.MAVLink_radio_status_message(200, 190, 50, 10, 10, 0, 0)
    beat = ml.MAVLink_heartbeat_message(ml.MAV_TYPE_GCS, ml.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
    before = check.unsigned_refused
    signed.spoofer.sendto(_pack(unsigned, radio), signed.vehicle_addr)
    signed.spoofer.sendto(_pack(unsigned, beat), signed.vehicle_addr)
    signed.receive(0.5)
    assert check.unsigned_refused == before + 1  # the heartbeat; the radio status passed


def test_a_forged_frame_cannot_lock_out_the_real_sender():
    """pymavlink records a stream's timestamp before it checks the signature, so one forged
    frame with a far-future timestamp makes the genuine ones look like replays; ours does not."""
    good = _encoder(255, KEY)
    forged = _encoder(255, OTHER_KEY)
    forged.signing.timestamp = good.signing.timestamp + 10**9
    check = bridge_signing.SignatureCheck(KEY)  # the one checker, the simulator's too
    beat = ml.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3)
    assert check.accept(_pack(good, beat), 0)
    assert not check.accept(_pack(forged, beat), 0)
    assert check.accept(_pack(good, beat), 0)  # still accepted
    first = _pack(good, beat)
    assert check.accept(first, 0) and not check.accept(first, 0)  # an exact replay
    stale = ml.MAVLink(None, 255, 190)  # a frame recorded two minutes ago, on a new stream
    stale.signing.secret_key, stale.signing.link_id, stale.signing.sign_outgoing = KEY, 9, True
    stale.signing.timestamp = bridge_signing.signing_clock() - 2 * 60 * 100_000
    assert not check.accept(_pack(stale, beat), 0)


def test_an_encoder_set_up_minutes_before_it_speaks_is_heard_by_a_new_receiver():
    """pymavlink only counts frames on from the time signing was set up: a node set up three
    minutes before its first swarm frame reaches a ground station (or a neighbour) that never
    heard it would be refused as a replay; ours stamps each frame with the wall clock."""
    node = _encoder(3, KEY, link_id=3)
    node.signing.timestamp = bridge_signing.signing_clock() - 3 * 60 * 100_000  # set up then
    beat = ml.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3)
    ground = bridge_signing.SignatureCheck(KEY)
    first = _pack(node, beat)
    assert ground.accept(first, 0) and ground.replays == 0
    assert ground.accept(_pack(node, beat), 0)  # later frames too, in order
    assert not ground.accept(first, 0)  # and a replay is still one


def test_keys_come_from_a_file_or_the_environment(tmp_path: Path):
    hex_file, raw_file, bad_file = tmp_path / "k.hex", tmp_path / "k.bin", tmp_path / "bad"
    hex_file.write_text(f"  {KEY_HEX}\n")
    raw_file.write_bytes(KEY)
    bad_file.write_text("0123")
    assert bridge_signing.load_signing_key(hex_file, {}) == KEY
    assert bridge_signing.load_signing_key(raw_file, {}) == KEY
    assert bridge_signing.load_signing_key(None, {"SWARMPLAN_SIGNING_KEY": KEY_HEX}) == KEY
    assert bridge_signing.load_signing_key(None, {}) is None
    with pytest.raises(bridge_signing.SigningKeyError, match="64 hex characters"):
        bridge_signing.load_signing_key(bad_file, {})
    with pytest.raises(bridge_signing.SigningKeyError, match="SWARMPLAN_SIGNING_KEY"):
        bridge_signing.load_signing_key(None, {"SWARMPLAN_SIGNING_KEY": "zz"})


def test_sim_cli_bad_key_is_one_line_exit_2(tmp_path: Path):
    bad = tmp_path / "bad.key"
    bad.write_text("not a key")
    for extra, environ in (
        (["--signing-key-file", str(bad)], env()),
        ([], env(SWARMPLAN_SIGNING_KEY="1234")),
    ):
        proc = run_swarmplan(["sim", "--duration-s", "1", *extra], timeout=60, environ=environ)
        assert proc.returncode == 2
        assert "signing key" in proc.stderr and "Traceback" not in proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1


def test_the_simulator_makes_its_key_file_once(tmp_path: Path):
    """``swarmplan sim --signing-key-file K`` with no K makes one (64 hex characters, mode 0600,
    said in one line) and signs with it; an existing key file is kept, never replaced."""
    key_file = tmp_path / "mission.key"
    args = ["sim", "--fast", "--duration-s", "0.1", "--signing-key-file", str(key_file)]
    first = run_swarmplan(args, 60)
    assert first.returncode == 0, first.stderr[-2000:]
    assert f"made a signing key for this mission in {key_file}" in first.stdout
    assert stat.S_IMODE(key_file.stat().st_mode) == 0o600
    key = bridge_signing.load_signing_key(key_file, {})
    assert len(key) == 32 and key.hex() not in first.stdout + first.stderr
    assert "unsigned_refused" in first.stdout.splitlines()[-1]  # its summary: signing was on
    assert bridge_signing.load_or_create_key_file(key_file) == (key, False)
    assert list(tmp_path.iterdir()) == [key_file]  # no partial file left behind


@pytest.mark.timeout(60)
def test_a_daemon_flying_unsigned_says_so_in_one_line_at_start(tmp_path: Path):
    """No key: one line saying so before anything else happens (here: no vehicle answers, and
    the daemon ends in one line of its own). Signed, it says nothing of the kind
    (tests/cli/test_two_shell_demo.py)."""
    args = ["daemon", "--connect", f"udpin:127.0.0.1:{free_udp_port()}", "--timeout", "1",
            "--no-view", "--out", str(tmp_path / "out")]  # fmt: skip
    proc = run_swarmplan(args, 50)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    said = [line for line in proc.stderr.splitlines() if "flying unsigned" in line]
    assert len(said) == 1 and "--signing-key-file" in said[0], proc.stderr[-2000:]
    assert proc.stderr.splitlines()[0] == said[0]  # at start: the first thing it says
