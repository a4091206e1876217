"""Bad datagrams are counted and ignored, never disturb a vehicle, never cost a good datagram."""

from __future__ import annotations

import os
import socket

os.environ.setdefault("MAVLINK20", "1")

from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402

from sim_gateway.mavlink_endpoint import DatagramParser, LinkStats  # noqa: E402


def _frame(message, sysid=255, compid=190) -> bytes:
    return bytes(message.pack(ml.MAVLink(None, sysid, compid)))


HEARTBEAT = ml.MAVLink_heartbeat_message(ml.MAV_TYPE_GCS, ml.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)


def _bad_crc(frame: bytes) -> bytes:
    return frame[:-1] + bytes([frame[-1] ^ 0xFF])


def _unknown_id(frame: bytes) -> bytes:
    raw = bytearray(frame)
    raw[7:10] = (60_000).to_bytes(3, "little")  # a message id no dialect has
    return bytes(raw)


def test_parser_counts_each_kind_of_bad_datagram_and_keeps_every_good_one():
    stats = LinkStats()
    parser = DatagramParser(stats)
    good = _frame(HEARTBEAT)
    bad = [b"\x00garbage\xff" * 7, _bad_crc(good), _unknown_id(good), good[:12], b"\xfd\x09\x00"]
    kept = 0
    for junk in bad * 20:
        assert parser.parse(junk) == []
        kept += len(parser.parse(good))  # the next good datagram always gets through
    assert kept == len(bad) * 20
    assert stats.bad_datagrams == len(bad) * 20
    assert stats.unknown_messages == 20


def test_junk_in_front_of_a_frame_in_the_same_datagram_does_not_swallow_it():
    parser = DatagramParser(LinkStats())
    good = _frame(HEARTBEAT)
    messages = parser.parse(b"\xfd\x09junk" + good + b"\xfe\x05tail")
    assert [m.get_type() for m in messages] == ["HEARTBEAT"]
    two = parser.parse(good + _bad_crc(good) + good)
    assert len(two) == 2


def test_bad_datagrams_over_udp_leave_vehicles_flying(gcs, sim_factory):
    running = sim_factory(speedup=5.0, airborne=True)
    sim = running.sim
    target = ("127.0.0.1", sim.sockets[0].local_port)
    good_cmd = ml.MAVLink_command_long_message(
        1, 1, ml.MAV_CMD_REQUEST_MESSAGE, 0, 242, 0, 0, 0, 0, 0, 0
    )
    out_of_range = ml.MAVLink_command_long_message(
        1, 1, ml.MAV_CMD_DO_SET_MODE, 0, 1, 1e9, 0, 0, 0, 0, 0
    )
    mav = ml.MAVLink(None, 255, 190)
    junk = [b"\x00" * 40, b"\xfd" * 300, os.urandom(64), _unknown_id(_frame(HEARTBEAT))]
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        acks = 0
        for k in range(20):
            sender.sendto(junk[k % len(junk)], target)
            sender.sendto(_bad_crc(bytes(good_cmd.pack(mav))), target)
            sender.sendto(bytes(out_of_range.pack(mav)), target)
            sender.sendto(bytes(good_cmd.pack(mav)), target)
            mav.seq = (mav.seq + 1) % 256
            ack = gcs.wait("COMMAND_ACK", 1, cond=lambda m: m.command == ml.MAV_CMD_REQUEST_MESSAGE)
            acks += ack is not None and ack.result == ml.MAV_RESULT_ACCEPTED
    finally:
        sender.close()
    assert acks == 20
    assert sim.stats.bad_datagrams >= 40
    assert sim.stats.unknown_messages >= 5
    assert sim.stats.rejected_commands >= 20
    assert sim.fleet.airborne.all() and all(v.armed for v in sim.vehicles)
    assert all(v.mode == 12 for v in sim.vehicles)  # still in LOITER
