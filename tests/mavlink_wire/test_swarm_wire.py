"""The swarm link's wire format (mavlink_wire/swarm_wire.py): reports go through real UDP on
127.0.0.1 as signed MAVLink TUNNEL frames, fragmented and put back together in any order; lost,
inconsistent and hostile fragments are dropped and counted, never raised; the worst case of a
paper scenario fits the radio budget of the swarm link (3.6 kB per UAV per step)."""

from __future__ import annotations

import math
import os

os.environ.setdefault("MAVLINK20", "1")

import random  # noqa: E402
import socket  # noqa: E402

import pytest  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402

from mavlink_wire.signing import SignatureCheck, mission_key, sign_outgoing  # noqa: E402
from mavlink_wire.swarm_budget import wire_bytes, worst_case_report  # noqa: E402
from mavlink_wire.swarm_wire import (  # noqa: E402
    FRAGMENT_HEADER,
    SWARM_PAYLOAD_TYPE,
    WIRE_VERSION,
    Claim,
    Engagement,
    Look,
    NodeState,
    SwarmReassembler,
    SwarmReport,
    SwarmSender,
    ThreatReport,
    WireError,
    encode_report,
    fragment_payloads,
    tunnel_message,
)
from planner.grid import Grid  # noqa: E402
from planner.scenario import load_scenario  # noqa: E402

BUDGET_BYTES = 3600  # 57.6 kbit/s shared by 20 UAVs at 10 s steps


def _report(uav: int = 3, looks: int = 12) -> SwarmReport:
    rng = random.Random(uav)
    return SwarmReport(
        uav=uav,
        step=217,
        state=NodeState((41, 77), 5, 41.512, 77.03, 17.318403629, True, math.radians(123.45),
                        123.45),  # fmt: skip
        looks=tuple(
            Look(
                k,
                217,
                (rng.randrange(100), rng.randrange(100)),
                tuple(rng.random() < 0.2 for _ in range(29)),
            )
            for k in range(looks)
        ),  # fmt: skip
        engagements=(Engagement(11, (60, 85), 216, True), Engagement(0, (12, 3), 210, False)),
        serviced=(2, 11, 14),
        claims=(Claim((42, 78), 2),),
        threats=(ThreatReport(63.0, 30.0, 6.0), ThreatReport(5.0, 40.0, 2.0)),
    )


@pytest.fixture
def udp_pair():
    """A sender and a receiver socket on 127.0.0.1 (free ports), closed after the test."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2.0)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    yield tx, rx
    tx.close()
    rx.close()


def _receive(rx: socket.socket, count: int) -> list[ml.MAVLink_message]:
    parser = ml.MAVLink(None)
    out = []
    for _ in range(count):
        data = rx.recv(65535)
        out.append(parser.decode(bytearray(data)))
    return out


def test_signed_report_round_trip_over_udp(udp_pair):
    tx, rx = udp_pair
    key = mission_key()
    report = _report()
    mav = ml.MAVLink(None, srcSystem=4, srcComponent=ml.MAV_COMP_ID_ONBOARD_COMPUTER)
    sign_outgoing(mav, key, link_id=4)
    frames = SwarmSender(report.uav).frames(report, mav)
    assert len(frames) >= 2  # the report is fragmented
    for frame in frames:
        tx.sendto(frame, rx.getsockname())
    receiver = SwarmReassembler(signature=SignatureCheck(key))
    got = [receiver.accept_message(m, 0.0) for m in _receive(rx, len(frames))]
    assert [r for r in got if r is not None] == [report]
    assert receiver.stats.messages == 1 and receiver.stats.frames == len(frames)
    # the same frames again are refused as replays by the signature check
    assert all(receiver.accept_message(ml.MAVLink(None).decode(bytearray(f)), 0.1) is None
               for f in frames)  # fmt: skip
    assert receiver.stats.unsigned_or_forged == len(frames)


def test_fragments_in_any_order_and_repeated_make_one_report(udp_pair):
    """Unsigned (a signed stream refuses what arrives out of order, as MAVLink signing does)."""
    tx, rx = udp_pair
    report = _report(looks=40)
    mav = ml.MAVLink(None, srcSystem=4, srcComponent=ml.MAV_COMP_ID_ONBOARD_COMPUTER)
    frames = SwarmSender(report.uav).frames(report, mav)
    assert len(frames) >= 4
    order = frames + frames[:2]
    random.Random(1).shuffle(order)
    for frame in order:
        tx.sendto(frame, rx.getsockname())
    receiver = SwarmReassembler()
    got = [receiver.accept_message(m, 0.0) for m in _receive(rx, len(order))]
    assert [r for r in got if r is not None] == [report]
    assert receiver.stats.duplicates == 2 and receiver.stats.messages == 1


def test_forged_and_unsigned_frames_are_refused_with_signing(udp_pair):
    tx, rx = udp_pair
    key = mission_key()
    report = _report(looks=0)
    forger = ml.MAVLink(None, srcSystem=4, srcComponent=191)
    sign_outgoing(forger, mission_key(), link_id=4)  # another key
    plain = ml.MAVLink(None, srcSystem=4, srcComponent=191)
    frames = SwarmSender(4).frames(report, forger) + SwarmSender(4).frames(report, plain)
    for frame in frames:
        tx.sendto(frame, rx.getsockname())
    receiver = SwarmReassembler(signature=SignatureCheck(key))
    assert all(receiver.accept_message(m, 0.0) is None for m in _receive(rx, len(frames)))
    assert receiver.stats.unsigned_or_forged == len(frames)
    assert receiver.stats.messages == 0


def test_missing_and_inconsistent_fragments_are_dropped_and_counted():
    sender = SwarmSender(7)
    payloads = [bytes(m.payload[: m.payload_length]) for m in sender.messages(_report(7))]
    assert len(payloads) >= 2
    receiver = SwarmReassembler(timeout_s=5.0)
    # a message missing its last fragment: given up after the timeout
    for p in payloads[:-1]:
        assert receiver.accept_payload(p, 0.0) is None
    assert receiver.accept_payload(b"", 10.0) is None  # any arrival expires the old ones
    assert receiver.stats.incomplete == 1
    # a fragment whose data was changed on the way (same header): the message fails its CRC
    second = [bytes(m.payload[: m.payload_length]) for m in sender.messages(_report(7))]
    bad = bytearray(second[0])
    bad[-1] ^= 0x55
    for p in [bytes(bad), *second[1:]]:
        assert receiver.accept_payload(p, 11.0) is None
    assert receiver.stats.inconsistent == 1
    # fragments of one sequence number that disagree on the count: dropped
    third = [bytes(m.payload[: m.payload_length]) for m in sender.messages(_report(7, looks=80))]
    other = bytearray(third[1])
    other[5] = len(third) + 1  # fragment count
    receiver.accept_payload(third[0], 12.0)
    receiver.accept_payload(bytes(other), 12.0)
    assert receiver.stats.inconsistent == 2
    # and a whole message afterwards still comes through
    fourth = [bytes(m.payload[: m.payload_length]) for m in sender.messages(_report(7))]
    assert [receiver.accept_payload(p, 13.0) for p in fourth][-1] == _report(7)


def test_hostile_bytes_never_raise_and_are_all_counted(udp_pair):
    """40,000 random payloads, half behind a plausible fragment header (so they reach the
    reassembly and the decoder), 5,000 mutations of real fragments, and 500 random TUNNEL
    frames through UDP: nothing raises; every fragment is counted somewhere."""
    rng = random.Random(27)
    receiver = SwarmReassembler(timeout_s=1.0, max_pending=16)
    real = [bytes(m.payload[: m.payload_length]) for m in SwarmSender(9).messages(_report(9))]
    fed = 0
    for k in range(40_000):
        body = rng.randbytes(rng.randrange(0, 129))
        if k % 2:
            count = rng.randrange(1, 4)
            header = FRAGMENT_HEADER.pack(
                WIRE_VERSION,
                rng.randrange(4),
                rng.randrange(8),
                rng.randrange(count),
                count,
                rng.randrange(65536),
            )
            body = (header + body)[:128]  # fmt: skip
        receiver.accept_payload(body, k * 0.001)
        fed += 1
    for k in range(5_000):
        p = bytearray(rng.choice(real))
        for _ in range(rng.randrange(1, 4)):
            p[rng.randrange(len(p))] = rng.randrange(256)
        receiver.accept_payload(bytes(p), 40.0 + k * 0.001)
        fed += 1
    tx, rx = udp_pair
    mav = ml.MAVLink(None, srcSystem=2, srcComponent=191)
    for _ in range(500):
        length = rng.randrange(0, 256)
        msg = ml.MAVLink_tunnel_message(0, 0, SWARM_PAYLOAD_TYPE, length,
                                        list(rng.randbytes(128)))  # fmt: skip
        tx.sendto(bytes(msg.pack(mav)), rx.getsockname())
        receiver.accept_message(_receive(rx, 1)[0], 50.0)
    s = receiver.stats
    held = sum(len(p.parts) for p in receiver._pending.values())
    assert s.bad_fragments + s.duplicates + s.frames == fed + 500 - s.foreign - s.unsigned_or_forged
    assert s.frames >= held and s.bad_fragments > 0 and s.frames > 0
    # still works afterwards
    ok = [receiver.accept_payload(p, 60.0) for p in fragment_payloads(encode_report(_report(5)),
                                                                       5, 999)]  # fmt: skip
    assert ok[-1] == _report(5)


def test_values_the_format_cannot_carry_are_refused_at_the_sender():
    with pytest.raises(WireError):
        encode_report(SwarmReport(1, 1, state=NodeState((70_000, 1), 0, 0.0, 0.0, 1.0)))
    with pytest.raises(WireError):
        encode_report(SwarmReport(1, 1, looks=(Look(1, 1, (1, 1), (True,) * 300),)))
    with pytest.raises(WireError):
        encode_report(SwarmReport(300, 1))
    with pytest.raises(WireError):
        encode_report(SwarmReport(1, 1, state=NodeState((1, 1), 8, 0.0, 0.0, 1.0)))


@pytest.mark.parametrize("name", ["paper-10uav", "paper-20uav"])
def test_worst_case_of_a_paper_scenario_fits_the_radio_budget(name):
    scenario = load_scenario(name)
    cfg = scenario.config
    footprint = len(Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km).disc_offsets(
        cfg.detection_radius_km))  # fmt: skip
    n = scenario.uav_count
    # relaying every other UAV's look too, signed
    worst = worst_case_report(n, footprint, len(scenario.targets), len(scenario.threats), n)
    size = wire_bytes(worst, signed=True)
    assert size <= BUDGET_BYTES
    assert n * size * 8 / cfg.step_s <= 57_600
    # and it decodes to itself
    receiver = SwarmReassembler()
    out = [receiver.accept_message(m, 0.0) for m in SwarmSender(worst.uav).messages(worst)]
    assert out[-1] == worst


def test_tunnel_message_is_broadcast_of_the_project_payload_type():
    msg = tunnel_message(b"\x01\x02")
    assert (msg.target_system, msg.target_component) == (0, 0)
    assert msg.payload_type == SWARM_PAYLOAD_TYPE > 32767  # MAVLink's private range
