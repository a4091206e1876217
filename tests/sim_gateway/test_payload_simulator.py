"""``swarmplan payload`` against a scripted autopilot on a real TCP socket (the way it sits on an
ArduPilot SITL's SERIAL1): it connects (and reconnects) to the autopilot's port, looks once per
decision period of the autopilot's own clock while airborne, with the encoding of our simulator's
camera, and resolves engagement captures against ground truth."""

from __future__ import annotations

import json
import os
import socket
import time

os.environ.setdefault("MAVLINK20", "1")

from loopback import start_swarmplan, stop  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from mavlink_wire.looks import parse_look_url  # noqa: E402
from planner.geodesy import local_km_to_geodetic  # noqa: E402
from planner.grid import Grid  # noqa: E402
from planner.scenario import load_scenario  # noqa: E402

SCENARIO = load_scenario("arduplane-3uav")
STEP_MS = round(SCENARIO.config.step_s * 1000)


class ScriptedAutopilot:
    """A TCP server speaking as autopilot (system id 2, component 1) to whoever connects."""

    def __init__(self) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.conn: socket.socket | None = None
        self.mav = mavlink.MAVLink(None, 2, 1)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.inbox: list = []

    def accept(self, timeout_s: float = 10.0) -> None:
        self.server.settimeout(timeout_s)
        self.conn, _ = self.server.accept()
        self.conn.settimeout(0.05)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True

    def send(self, msg) -> None:
        assert self.conn is not None
        self.conn.sendall(msg.pack(self.mav))

    def fly(self, time_boot_ms: int, x_km: float, y_km: float, armed: bool = True) -> None:
        lat, lon = local_km_to_geodetic(x_km, y_km, SCENARIO.origin)
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        self.send(mavlink.MAVLink_heartbeat_message(1, 3, base, 15, 4, 3))
        self.send(
            mavlink.MAVLink_global_position_int_message(
                time_boot_ms, round(lat[0] * 1e7), round(lon[0] * 1e7), 684000,
                100000 if armed else 0, 0, 0, 0, 0,
            )
        )  # fmt: skip

    def receive(self, kind: str, timeout_s: float = 5.0, cond=lambda m: True):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for i, m in enumerate(self.inbox):
                if m.get_type() == kind and cond(m):
                    return self.inbox.pop(i)
            try:
                data = self.conn.recv(65536)
            except TimeoutError:
                continue
            if not data:
                return None
            self.inbox += self.parser.parse_buffer(data) or []
        return None

    def close_client(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    def close(self) -> None:
        self.close_client()
        self.server.close()


def test_looks_on_the_vehicle_clock_and_engagements_from_ground_truth(tmp_path):
    autopilot = ScriptedAutopilot()
    # the payload simulator starts first and retries until the port accepts (SITL's SERIAL1
    # opens only once the autopilot has booted)
    proc = start_swarmplan(
        ["payload", "--scenario", "arduplane-3uav", "--seed", "1",
         "--connect", f"tcp:127.0.0.1:{autopilot.port}",
         "--target-account", str(tmp_path / "truth.json")],
        tmp_path / "payload.log",
    )  # fmt: skip
    try:
        autopilot.accept()
        grid = Grid(SCENARIO.config.grid_nx, SCENARIO.config.grid_ny, SCENARIO.config.cell_km)
        # on the ground: heard (the camera's heartbeat comes), but no look
        autopilot.fly(1000, 5.5, 1.5, armed=False)
        hb = autopilot.receive("HEARTBEAT", cond=lambda m: m.get_srcComponent() == 100)
        assert hb is not None and hb.get_srcSystem() == 2 and hb.type == mavlink.MAV_TYPE_CAMERA
        autopilot.fly(STEP_MS + 10, 5.5, 1.5, armed=False)
        assert autopilot.receive("CAMERA_IMAGE_CAPTURED", timeout_s=1.0) is None
        # airborne: the first fix arms the clock, each new decision period brings one look
        spot = (1.5, 8.5)  # target 5 (stationary, unknown position): its ground truth
        looks = []
        for k, period in enumerate((2, 2, 3, 5)):
            autopilot.fly(period * STEP_MS + 100 + k, *spot)
            if k in (2, 3):
                look = autopilot.receive("CAMERA_IMAGE_CAPTURED")
                assert look is not None and look.get_srcComponent() == 100
                looks.append(look)
        assert [m.image_index for m in looks] == [0, 1]
        assert looks[0].time_boot_ms == 3 * STEP_MS + 102
        footprint = {tuple(o) for o in grid.disc_offsets(SCENARIO.config.detection_radius_km)}
        for look in looks:
            offsets = parse_look_url(look.file_url)
            assert set(offsets) <= footprint
        # engagement at the target: ACCEPTED from the camera, the target's id; a repeat replays
        autopilot.send(mavlink.MAVLink_command_long_message(2, 100, 2000, 0, 0, 0, 1, 7, 0, 0, 0))
        ack = autopilot.receive("COMMAND_ACK")
        assert ack is not None and ack.get_srcComponent() == 100
        assert (ack.result, ack.result_param2, ack.progress) == (0, 5, 7)
        autopilot.send(mavlink.MAVLink_command_long_message(2, 100, 2000, 1, 0, 0, 1, 7, 0, 0, 0))
        ack = autopilot.receive("COMMAND_ACK")
        assert (ack.result, ack.result_param2) == (0, 5)
        # a new request at the same spot: the target left the world with the first engagement
        autopilot.send(mavlink.MAVLink_command_long_message(2, 100, 2000, 0, 0, 0, 1, 8, 0, 0, 0))
        ack = autopilot.receive("COMMAND_ACK")
        assert (ack.result, ack.result_param2) == (0, 0)
        # a malformed request is DENIED
        autopilot.send(mavlink.MAVLink_command_long_message(2, 100, 2000, 0, 0, 5, 1, 9, 0, 0, 0))
        ack = autopilot.receive("COMMAND_ACK")
        assert ack.result == mavlink.MAV_RESULT_DENIED
        # the autopilot's port goes away and comes back: the camera reconnects and goes on
        autopilot.close_client()
        autopilot.accept()
        autopilot.fly(6 * STEP_MS + 5, *spot)
        look = autopilot.receive("CAMERA_IMAGE_CAPTURED")
        assert look is not None and look.image_index == 2
    finally:
        code = stop(proc)
        autopilot.close()
    lines = (tmp_path / "payload.log").read_text().splitlines()
    summary = json.loads(lines[-1])
    assert code == 0
    assert summary["targets_engaged"] == [5] and summary["looks_per_vehicle"][1] == 3
    # the truth half of the per-target account: a step per look instant, stamped with the
    # vehicle's clock, and the engagement of target 5 by UAV 1 (system id 2)
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert truth["times_ms"][0] == 3 * STEP_MS + 102 and len(truth["steps"]) == 3
    five = next(i for i, t in enumerate(truth["targets"]) if t["id"] == 5)
    # in the footprint at both looks before its engagement; serviced, it is gone at the third
    assert [five in inside for inside in truth["in_footprint"]] == [True, True, False]
    assert truth["targets"][five]["engaged_uav"] == 1
    assert truth["targets"][five]["engaged_step"] == truth["steps"][1]


def test_bad_endpoint_is_one_line(tmp_path):
    from loopback import run_swarmplan

    done = run_swarmplan(["payload", "--connect", "serial:/dev/null"], timeout=30)
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "is not an endpoint" in done.stderr


def test_a_udpout_autopilot_that_opens_its_port_late_is_still_heard(tmp_path):
    """PX4's onboard link answers only whoever spoke to it first: a payload simulator started
    before the port opened keeps saying hello until the autopilot answers, then is its camera."""
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # a free port that nobody listens on yet: the first hello is lost
    proc = start_swarmplan(
        ["payload", "--scenario", "arduplane-3uav", "--seed", "1",
         "--connect", f"udpout:127.0.0.1:{port}"],
        tmp_path / "payload.log",
    )  # fmt: skip
    autopilot = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        time.sleep(2.5)  # the simulator's first hello went to a closed port
        autopilot.bind(("127.0.0.1", port))
        autopilot.settimeout(0.2)
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        mav = mavlink.MAVLink(None, 2, 1)
        peer, camera = None, None
        deadline = time.monotonic() + 10
        while camera is None and time.monotonic() < deadline:
            try:
                data, address = autopilot.recvfrom(65535)
            except TimeoutError:
                data, address = b"", None
            for msg in parser.parse_buffer(data) or []:
                if msg.get_type() == "HEARTBEAT" and msg.get_srcSystem() == 2:
                    camera = msg
                elif msg.get_type() == "HEARTBEAT":
                    peer = address  # a hello: answer it as autopilot 2
            if peer is not None:
                hb = mavlink.MAVLink_heartbeat_message(1, 3, 0, 15, 4, 3)
                autopilot.sendto(hb.pack(mav), peer)
        assert peer is not None, "no hello reached the autopilot after it opened its port"
        assert camera is not None and camera.get_srcComponent() == 100
        assert camera.type == mavlink.MAV_TYPE_CAMERA
    finally:
        code = stop(proc)
        autopilot.close()
    assert code == 0
    summary = json.loads((tmp_path / "payload.log").read_text().splitlines()[-1])
    assert summary["vehicles_heard"] == 1
