"""Only the daemon drives a lockstep simulator's clock (issue 31, finding 2). A real simulator and
a real daemon over loopback UDP, and a stranger's socket sending lockstep grants (SYSTEM_TIME
without UTC) straight to the vehicles' ports: a release (0xFFFFFFFF) as system 77, a horizon an
hour ahead in the daemon's own system id, a release in a vehicle's system id. Before, one such
datagram released lockstep and the daemon stopped mid-mission (exit 2, blaming the operator's
flags); now each is dropped and counted (``foreign_grants``), and the mission flies every step.
With signing on, the same frames signed with the mission's key (a second ground station that
holds the key) are refused the same way, and unsigned ones never get past the signature."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import json  # noqa: E402
import socket  # noqa: E402
import threading  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from loopback import env, free_port_block, free_udp_port, start_swarmplan, stop  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402
from reliability_harness import KEY_HEX, last_json  # noqa: E402
from udp_fault_relay import FaultProfile, FaultRelay  # noqa: E402

from mavlink_bridge.daemon import DaemonOptions, MissionDaemon  # noqa: E402
from mavlink_bridge.lockstep_clock import LockstepReleasedError  # noqa: E402
from mavlink_bridge.signing import sign_outgoing  # noqa: E402
from planner.scenario import load_scenario  # noqa: E402

SCENARIO = "paper-10uav"
VEHICLES = 10
STEPS = 8
RELEASE = 0xFFFFFFFF
#: (system id, component id, time_boot_ms) of the spoofed grants, sent in turn
GRANTS = ((77, 190, RELEASE), (255, 190, 3_600_000), (1, 1, RELEASE))


class GrantSpoofer(threading.Thread):
    """A stranger on its own UDP socket sending the grants of :data:`GRANTS` in turn to every
    vehicle port ``base .. base + count - 1``, one datagram each ``period_s``, until stopped;
    with ``key``, every other frame is signed with it (a second ground station that holds the
    key), the others go unsigned."""

    def __init__(self, base: int, count: int, key: bytes | None, period_s: float = 0.005):
        super().__init__(daemon=True, name="grant-spoofer")
        self.ports = [base + i for i in range(count)]
        self.period_s = period_s
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.senders = {}  # (system, component, signed) -> its encoder
        for sysid, compid, _ in GRANTS:
            self.senders[sysid, compid, False] = ml.MAVLink(None, sysid, compid)
            if key is not None:
                self.senders[sysid, compid, True] = mav = ml.MAVLink(None, sysid, compid)
                sign_outgoing(mav, key, link_id=7)
        self.signing = key is not None
        self.sent = 0
        self._halt = threading.Event()

    def run(self) -> None:
        k = 0
        while not self._halt.wait(self.period_s):
            sysid, compid, boot_ms = GRANTS[k % len(GRANTS)]
            mav = self.senders[sysid, compid, self.signing and k // len(GRANTS) % 2 == 0]
            frame = ml.MAVLink_system_time_message(0, boot_ms).pack(mav)
            mav.seq = (mav.seq + 1) % 256  # each frame its own, as a sender's are
            try:
                self.sock.sendto(bytes(frame), ("127.0.0.1", self.ports[k % len(self.ports)]))
                self.sent += 1
            except OSError:
                pass  # the simulator not up yet, or gone
            k += 1

    def stop(self) -> None:
        self._halt.set()
        self.join(5)
        self.sock.close()


def fly_with_grant_spoofer(tmp_path: Path, *, signed: bool) -> tuple[int, dict, dict | None, str]:
    """A lockstep mission of STEPS steps (simulator and daemon as processes) while the spoofer
    sends grants to every vehicle port from before the first vehicle is heard to the end: the
    daemon's exit status, result, the simulator's summary and the daemon's log."""
    port, base = free_udp_port(), free_port_block(VEHICLES)
    key_file = tmp_path / "mission.key"
    key_file.write_text(KEY_HEX + "\n")
    sim_log, daemon_log = tmp_path / "sim.log", tmp_path / "daemon.log"
    spoofer = GrantSpoofer(base, VEHICLES, bytes.fromhex(KEY_HEX) if signed else None)
    spoofer.start()  # it talks first: before the simulator and the daemon exist
    sim = start_swarmplan(
        ["sim", "--scenario", SCENARIO, "--seed", "4", "--lockstep", "--speedup", "100",
         "--gcs-port", str(port), "--bind-base-port", str(base), "--quiet"],
        sim_log,
        env(SWARMPLAN_SIGNING_KEY=KEY_HEX) if signed else env(),
    )  # fmt: skip
    args = [
        "daemon", "--connect", f"udpin:127.0.0.1:{port}", "--scenario", SCENARIO,
        "--seed", "4", "--steps", str(STEPS), "--lockstep", "--timeout", "30",
        "--out", str(tmp_path / "out"), "--json", "--no-view",
    ]  # fmt: skip
    if signed:
        args += ["--signing-key-file", str(key_file)]
    daemon = start_swarmplan(args, daemon_log, stdout_pipe=True)
    try:
        stdout, _ = daemon.communicate(timeout=150)
    finally:
        sent = spoofer.sent
        spoofer.stop()
        stop(daemon)
        stop(sim)
    assert sent > 100, sent
    log = daemon_log.read_text(errors="replace")
    assert "Traceback" not in log, log[-3000:]
    result = json.loads(stdout) if stdout.strip() else {"steps": 0}
    return daemon.returncode, result, last_json(sim_log), log


@pytest.mark.timeout(200)
@pytest.mark.parametrize("signed", [False, True], ids=["unsigned", "signed-by-a-second-station"])
def test_grants_from_a_stranger_neither_release_nor_advance_the_clock(tmp_path: Path, signed):
    """Finding 2: one SYSTEM_TIME(0, 0xFFFFFFFF) from system 77 released lockstep and the mission
    stopped at step 16 of 200, exit 2. Here thousands of grants reach every vehicle port, from
    before the vehicles start to the end: the mission flies every step, the simulator stays in
    lockstep, and every grant is dropped and counted."""
    code, result, summary, log = fly_with_grant_spoofer(tmp_path, signed=signed)
    assert code == 0, log[-3000:]
    assert result["steps"] == STEPS and result["lost_uavs"] == []
    assert summary is not None
    # every grant that reached the simulator, counted, until the daemon released it at the end
    if signed:  # the unsigned half never gets past the signature
        assert summary["unsigned_refused"] > 300 and summary["foreign_grants"] > 200, summary
    else:
        assert summary["foreign_grants"] > 500, summary
    assert summary["safety"]["threat_entries"] == 0


@pytest.mark.timeout(200)
def test_a_release_from_the_ground_stations_own_address_is_named_as_such(tmp_path: Path):
    """Without signing, a sender on the path (here the relay's socket of vehicle 3, the very
    address the vehicle sends to, in the daemon's system id) can still release the clock. The
    daemon then stops in one line, as before, but no longer tells the operator to restart the
    simulator with --lockstep as if it had been started without: the simulator held at every
    grant so far, so the line says something released it, and what can have."""
    scenario = load_scenario(SCENARIO)
    relay_holder: list[FaultRelay] = []

    def release_at_step_2(status) -> None:
        relay = relay_holder[0]
        if status.step == 2 and relay.vehicle_addr[2] is not None:
            relay.socks[2].sendto(grant_frame(RELEASE, 255, 190), relay.vehicle_addr[2])

    daemon = MissionDaemon(
        scenario,
        DaemonOptions(
            connect=["udpin:127.0.0.1:0"], seed=5, steps=STEPS, lockstep=True,
            discovery_timeout_s=60, rtl_watch_s=0.0, on_step=release_at_step_2,
        ),
    )  # fmt: skip
    link = daemon.connect()
    relay = FaultRelay(link.endpoints[0].port, VEHICLES, FaultProfile(), seed=5)
    relay_holder.append(relay)
    relay.start()
    sim = start_swarmplan(
        ["sim", "--scenario", SCENARIO, "--seed", "5", "--lockstep", "--speedup", "100",
         "--per-vehicle-ports", str(relay.base_port), "--quiet"],
        tmp_path / "sim.log",
    )  # fmt: skip
    try:
        with pytest.raises(LockstepReleasedError) as raised:
            daemon.fly()
    finally:
        stop(sim)
        relay.stop()
    said = str(raised.value)
    assert "ran past the granted simulated time" in said, said
    assert "after holding at each of our grants up to" in said, said
    assert "another ground station or a stranger on its link" in said, said
    assert "started without --lockstep" not in said, said
    assert daemon.report is not None and daemon.report.result["steps"] >= 2


def grant_frame(boot_ms: int, sysid: int, compid: int) -> bytes:
    return bytes(ml.MAVLink_system_time_message(0, boot_ms).pack(ml.MAVLink(None, sysid, compid)))
