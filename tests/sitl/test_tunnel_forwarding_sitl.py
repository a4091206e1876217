"""Does a real ArduPlane (``ARDUPLANE_SITL``) forward the swarm link between its ports? A
companion computer's node on SERIAL2 (TCP 5763+10N, system 1 component 191, heartbeat as
MAV_TYPE_ONBOARD_CONTROLLER) sends swarm-link TUNNEL frames (target 0/0, payload type 0xA557,
fragmented report); a telemetry side on SERIAL0 (TCP 5760+10N, system 255) must receive them
byte for byte and reassemble the report, and the same the other way (what a radio relay between
planes delivers to a plane reaches its node). ArduPilot routes broadcast messages to every other
link once it has seen traffic there (docs/onboard.md, "Does ArduPilot forward it?")."""

from __future__ import annotations

import os
import time

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402
from sitl_harness import _listening, homes_near  # noqa: E402

from mavlink_wire.signing import SignatureCheck, mission_key, sign_outgoing  # noqa: E402
from mavlink_wire.swarm_wire import (  # noqa: E402
    SWARM_PAYLOAD_TYPE,
    Look,
    NodeState,
    SwarmReassembler,
    SwarmReport,
    SwarmSender,
)

ROUNDS = 10  # reports each way, each of several TUNNEL frames


def _connect(url: str, system: int, component: int, timeout_s: float = 20.0):
    conn = mavutil.mavlink_connection(
        url, source_system=system, source_component=component, autoreconnect=False
    )
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        m = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.2)
        if m is not None and m.get_srcComponent() == 1:
            return conn
    conn.close()
    raise AssertionError(f"no autopilot heartbeat on {url} within {timeout_s:g} s")


def _beat(conn, kind: int) -> None:
    conn.mav.heartbeat_send(kind, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)


def _report(uav: int, step: int) -> SwarmReport:
    looks = tuple(Look(uav, step, (k, 2 * k), (k % 2 == 0,) * 29) for k in range(20))
    return SwarmReport(uav, step, NodeState((3, 4), 2, 3.5, 4.5, 20.0), looks)


def _send_and_collect(
    src, dst, uav: int, beats, check: SignatureCheck | None = None
) -> tuple[list[SwarmReport], int, int]:
    """``ROUNDS`` reports from ``src``, one every 0.2 s; what ``dst`` reassembled of them
    (checking signatures with ``check``), and the TUNNEL frames sent and received."""
    sender, receiver = SwarmSender(uav), SwarmReassembler(signature=check)
    sent = received = 0
    got: list[SwarmReport] = []
    for step in range(ROUNDS):
        beats()
        for message in sender.messages(_report(uav, step)):
            src.mav.send(message)
            sent += 1
        deadline = time.monotonic() + 0.2
        while time.monotonic() < deadline:
            m = dst.recv_match(type="TUNNEL", blocking=True, timeout=0.05)
            if m is None or m.payload_type != SWARM_PAYLOAD_TYPE:
                continue
            received += 1
            report = receiver.accept_message(m, time.monotonic())
            if report is not None:
                got.append(report)
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        m = dst.recv_match(type="TUNNEL", blocking=True, timeout=0.1)
        if m is not None and m.payload_type == SWARM_PAYLOAD_TYPE:
            received += 1
            report = receiver.accept_message(m, time.monotonic())
            if report is not None:
                got.append(report)
    return got, sent, received


def test_arduplane_forwards_swarm_tunnel_frames_between_serial0_and_serial2(sitl_swarm):
    swarm = sitl_swarm(homes_near(-35.36, 149.17, 1), speedup=1, params={"FENCE_ENABLE": 0})
    vehicle = swarm.vehicles[0]
    gcs = _connect(vehicle.master, 255, 190)
    serial2 = vehicle.port + 3
    deadline = time.monotonic() + 20
    while not _listening(serial2):
        assert time.monotonic() < deadline, "SERIAL2 never listened"
        time.sleep(0.1)
    node = _connect(f"tcp:127.0.0.1:{serial2}", vehicle.system_id, 191)
    try:
        onboard = mavutil.mavlink.MAV_TYPE_ONBOARD_CONTROLLER
        gcs_type = mavutil.mavlink.MAV_TYPE_GCS

        def beats() -> None:
            _beat(node, onboard)
            _beat(gcs, gcs_type)

        for _ in range(5):  # both sides heard on their links before the first frame
            beats()
            time.sleep(0.2)
        # both ends sign with the mission key (the autopilot itself has none set): the frames
        # reach the other side with their signature intact
        key = mission_key()
        sign_outgoing(node.mav, key, link_id=7)
        sign_outgoing(gcs.mav, key, link_id=8)
        up, sent_up, heard_up = _send_and_collect(node, gcs, 1, beats, SignatureCheck(key))
        down, sent_down, heard_down = _send_and_collect(gcs, node, 2, beats, SignatureCheck(key))
    finally:
        node.close()
        gcs.close()
    print(
        f"SERIAL2 -> SERIAL0: {heard_up}/{sent_up} frames, {len(up)}/{ROUNDS} reports; "
        f"SERIAL0 -> SERIAL2: {heard_down}/{sent_down} frames, {len(down)}/{ROUNDS} reports"
    )
    assert up == [_report(1, s) for s in range(ROUNDS)]
    assert down == [_report(2, s) for s in range(ROUNDS)]
    assert heard_up == sent_up and heard_down == sent_down
