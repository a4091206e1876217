"""``swarmplan radio-relay`` (sim_gateway/radio_relay.py), a real process between three TCP
servers that play autopilots' telemetry ports (docs/onboard.md, "On a companion computer"):
each says its HEARTBEAT and GLOBAL_POSITION_INT as ArduPlane does; plane 1 forwards its node's
swarm-link frames and heartbeat. The relay must carry the frames byte for byte to the planes in
range only, carry no heartbeat, and say its own heartbeat as no ground station."""

from __future__ import annotations

import json
import math
import os
import socket
import time

os.environ.setdefault("MAVLINK20", "1")

import numpy as np  # noqa: E402
from loopback import start_swarmplan, stop  # noqa: E402

from mavlink_wire.protocol import mavlink  # noqa: E402
from mavlink_wire.swarm_wire import NodeState, SwarmReport, SwarmSender  # noqa: E402
from planner.geodesy import local_km_to_geodetic  # noqa: E402
from planner.scenario import Origin  # noqa: E402
from sim_gateway.radio import SwarmRadio  # noqa: E402
from sim_gateway.radio_relay import RELAY_SYSTEM_ID  # noqa: E402
from sim_gateway.sim_options import RadioOptions  # noqa: E402

EAST_KM = (0.0, 5.0, 20.0)  # plane 2 hears plane 1 within 10 km, plane 3 does not
REPORTS = 10


class FakeAutopilot:
    """A TCP server with one client (the relay): what an ArduPilot serial port over TCP is."""

    def __init__(self, system_id: int, east_km: float) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.conn: socket.socket | None = None
        self.mav = mavlink.MAVLink(None, system_id, 1)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        lat, lon = local_km_to_geodetic(east_km, 0.0, Origin())
        self.lat_e7, self.lon_e7 = int(lat[0] * 1e7), int(lon[0] * 1e7)
        self.heard: list[mavlink.MAVLink_message] = []

    def accept(self, timeout_s: float) -> None:
        self.server.settimeout(timeout_s)
        self.conn, _ = self.server.accept()
        self.conn.settimeout(0.01)

    def say_state(self) -> None:
        beat = mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 15, 4, 3
        )
        where = mavlink.MAVLink_global_position_int_message(
            1000, self.lat_e7, self.lon_e7, 684_000, 100_000, 0, 0, 0, 0
        )
        self.send(bytes(beat.pack(self.mav)) + bytes(where.pack(self.mav)))

    def send(self, frames: bytes) -> None:
        assert self.conn is not None
        self.conn.sendall(frames)

    def read(self) -> None:
        assert self.conn is not None
        try:
            data = self.conn.recv(65536)
        except TimeoutError:
            return
        self.heard += [m for m in self.parser.parse_buffer(data) or () if m is not None]

    def close(self) -> None:
        for s in (self.conn, self.server):
            if s is not None:
                s.close()


def test_the_relay_carries_swarm_frames_in_range_and_no_heartbeat(tmp_path):
    planes = [FakeAutopilot(k + 1, x) for k, x in enumerate(EAST_KM)]
    log = tmp_path / "relay.log"
    ports = [a for p in planes for a in ("--connect", f"tcp:127.0.0.1:{p.port}")]
    relay = start_swarmplan(["radio-relay", "--radio-range-km", "10", "--quiet", *ports], log)
    try:
        for plane in planes:
            plane.accept(timeout_s=20)
        for _ in range(10):  # the planes located (positions every 0.1 s, as a stream would)
            for plane in planes:
                plane.say_state()
                plane.read()
            time.sleep(0.1)
        node = mavlink.MAVLink(None, 255, 190)  # plane 1's node, forwarded by its autopilot
        gcs_beat = mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4, 3
        )
        sender, sent = SwarmSender(0), []
        for step in range(REPORTS):
            planes[0].send(bytes(gcs_beat.pack(node)))
            for msg in sender.messages(SwarmReport(0, step, NodeState((3, 4), 2, 3.5, 4.5, 9.0))):
                frame = bytes(msg.pack(node))
                sent.append(frame)
                planes[0].send(frame)
            for plane in planes:
                plane.read()
            time.sleep(0.05)
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline:
            for plane in planes:
                plane.read()
            if sum(m.get_type() == "TUNNEL" for m in planes[1].heard) >= len(sent):
                break
    finally:
        stop(relay)
        for plane in planes:
            plane.close()
    tunnels = [[bytes(m.get_msgbuf()) for m in p.heard if m.get_type() == "TUNNEL"] for p in planes]
    assert tunnels == [[], sent, []]  # byte for byte, in order, to the plane in range only
    for plane in planes:  # no node's heartbeat crossed; the relay's own is no ground station's
        beats = [m for m in plane.heard if m.get_type() == "HEARTBEAT"]
        assert beats and {m.get_srcSystem() for m in beats} == {RELAY_SYSTEM_ID}
        assert all(m.type != mavlink.MAV_TYPE_GCS for m in beats)
    summary = json.loads(log.read_text().splitlines()[-1])
    assert summary["planes"] == [1, 2, 3]
    n = len(sent)
    assert (summary["frames_sent"], summary["delivered"], summary["lost_to_range"]) == (n, n, n)
    assert summary["not_relayed"]["HEARTBEAT"] >= REPORTS + 30
    assert math.isclose(summary["min_separation_km"], 5.0, abs_tol=0.05)


def test_a_plane_not_located_yet_neither_hears_nor_is_heard():
    """The radio model the relay shares with the simulator: NaN positions are out of range,
    even with unlimited range."""

    class Port:
        def send(self, frame: bytes) -> None:
            raise AssertionError("nothing may be sent")

    radio = SwarmRadio(RadioOptions(), [Port(), Port()], None, seed=1)
    located = np.array([[0.0, 0.0, 100.0], [np.nan, np.nan, np.nan]])
    assert radio.transmit(0, b"frame", located, 0.0) == []
    assert radio.transmit(1, b"frame", located, 0.0) == []
    assert radio.stats.lost_to_range == 2 and radio.stats.delivered == 0
