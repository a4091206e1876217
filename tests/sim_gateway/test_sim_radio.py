"""The simulator's swarm radio (sim_gateway/radio.py) over real UDP on 127.0.0.1: one node per
vehicle (a socket on the vehicle's per-vehicle port, talking to the vehicle's own socket) sends
swarm-link TUNNEL frames; the radio passes them to the nodes of the vehicles in range, loses
them with the loss probability, drops what exceeds the channel's rate, and counts all of it."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import socket  # noqa: E402
import time  # noqa: E402

import loopback  # noqa: E402
import pytest  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402
from sim_harness import RunningSim  # noqa: E402

from mavlink_wire.signing import SignatureCheck, mission_key, sign_outgoing  # noqa: E402
from mavlink_wire.swarm_wire import (  # noqa: E402
    Claim,
    Look,
    NodeState,
    SwarmReassembler,
    SwarmReport,
    SwarmSender,
)
from planner.scenario import load_scenario  # noqa: E402
from sim_gateway.sim_options import RadioOptions, SimOptions  # noqa: E402
from sim_gateway.simulator import Simulator  # noqa: E402


class Nodes:
    """One UDP socket per vehicle on consecutive free ports (the simulator's per-vehicle
    ports), each with its own reassembler."""

    def __init__(self, count: int, key: bytes | None = None) -> None:
        self.socks = loopback.bind_port_block(count)
        for s in self.socks:
            s.setblocking(False)
        self.base = self.socks[0].getsockname()[1]
        check = (lambda: SignatureCheck(key)) if key is not None else (lambda: None)
        self.receivers = [SwarmReassembler(signature=check()) for _ in range(count)]
        self.reports: list[list[SwarmReport]] = [[] for _ in range(count)]
        self.parsers = [ml.MAVLink(None) for _ in range(count)]

    def send(self, index: int, vehicle_port: int, frames: list[bytes]) -> None:
        for frame in frames:
            self.socks[index].sendto(frame, ("127.0.0.1", vehicle_port))

    def pump(self) -> None:
        for k, sock in enumerate(self.socks):
            while True:
                try:
                    data = sock.recv(65535)
                except (BlockingIOError, InterruptedError):
                    break
                try:
                    msgs = self.parsers[k].parse_buffer(data) or []
                except ml.MAVError:
                    continue
                for m in msgs:
                    report = self.receivers[k].accept_message(m, time.monotonic())
                    if report is not None:
                        self.reports[k].append(report)

    def close(self) -> None:
        for s in self.socks:
            s.close()


def _start(nodes: Nodes, radio: RadioOptions, positions_km, **options) -> RunningSim:
    """A simulator of len(positions_km) parked vehicles at the given (x, y) km, in front of
    ``nodes``, started in a thread."""
    opts = SimOptions(
        seed=5, vehicles=len(positions_km), boot_s=0.0, speedup=10.0, radio=radio,
        per_vehicle_port_base=nodes.base, **options,
    )  # fmt: skip
    sim = Simulator(load_scenario("paper-10uav"), opts)
    for i, (x, y) in enumerate(positions_km):
        sim.fleet.x_m[i], sim.fleet.y_m[i] = x * 1000.0, y * 1000.0
    return RunningSim(sim)


def _until(nodes: Nodes, done, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        nodes.pump()
        if done():
            return True
        time.sleep(0.02)
    return False


def _report(uav: int, step: int, looks: int = 1) -> SwarmReport:
    return SwarmReport(
        uav, step, NodeState((10, 20), 3, 10.5, 20.5, 20.0),
        tuple(Look(uav, step, (10, 20), (True, False) * 14 + (True,)) for _ in range(looks)),
        claims=(Claim((11, 21), 0),),
    )  # fmt: skip


@pytest.fixture
def nodes3():
    nodes = Nodes(3)
    yield nodes
    nodes.close()


def test_frames_reach_the_nodes_in_range_and_not_beyond(nodes3):
    nodes = nodes3
    running = _start(nodes, RadioOptions(range_km=10.0), [(20, 20), (27, 20), (45, 20)])
    try:
        sim = running.sim
        mav = ml.MAVLink(None, srcSystem=1, srcComponent=191)
        sender = SwarmSender(0)
        sent = [_report(0, step, looks=20) for step in range(1, 4)]  # several frames each
        frames = [f for r in sent for f in sender.frames(r, mav)]
        nodes.send(0, sim.sockets[0].local_port, frames)
        assert _until(nodes, lambda: len(nodes.reports[1]) == len(sent)), nodes.receivers[1].stats
        assert nodes.reports[1] == sent  # 7 km away: everything, in order
        time.sleep(0.3)
        nodes.pump()
        assert nodes.reports[2] == [] and nodes.receivers[2].stats.frames == 0  # 25 km away
        assert nodes.reports[0] == []  # the sender does not hear itself
        radio = sim.radio.stats
        assert radio.frames_sent == len(frames)
        assert radio.delivered == len(frames) and radio.lost_to_range == len(frames)
        assert radio.bytes_sent[0] == sum(len(f) for f in frames) == radio.bytes_received[1]
        assert radio.bytes_received[2] == 0
    finally:
        running.close()
    assert sim.summary()["radio"]["lost_to_range"] == len(frames)


def test_loss_is_drawn_per_receiver_and_counted(nodes3):
    nodes = nodes3
    running = _start(nodes, RadioOptions(loss=0.4), [(20, 20), (21, 20), (22, 20)])
    try:
        sim = running.sim
        mav = ml.MAVLink(None, srcSystem=1, srcComponent=191)
        sender = SwarmSender(0)
        count = 0
        for step in range(300):
            frames = sender.frames(_report(0, step, looks=12), mav)  # two frames each
            nodes.send(0, sim.sockets[0].local_port, frames)
            count += len(frames)
            if step % 20 == 0:
                nodes.pump()
        radio = sim.radio.stats
        heard = lambda: sum(r.stats.frames for r in nodes.receivers)  # noqa: E731
        assert _until(nodes, lambda: radio.frames_sent == count and heard() == radio.delivered)
        assert count == 600
        assert radio.delivered + radio.lost_to_loss == 2 * count  # two receivers each
        assert 0.3 < radio.lost_to_loss / (2 * count) < 0.5
        for k in (1, 2):  # a report whose two frames both came through is whole
            stats = nodes.receivers[k].stats
            assert stats.messages == len(nodes.reports[k]) > 0
            assert stats.inconsistent == 0 and stats.malformed == 0
        assert radio.lost_to_range == 0
    finally:
        running.close()


def test_bandwidth_limit_drops_what_the_channel_cannot_carry(nodes3):
    nodes = nodes3
    # 2 kbit/s: a ~158-byte frame takes 0.63 s of air; the backlog may be one decision period
    # (10 s): a burst of 60 frames cannot all go
    running = _start(nodes, RadioOptions(kbps=2.0), [(20, 20), (21, 20), (22, 20)])
    try:
        sim = running.sim
        mav = ml.MAVLink(None, srcSystem=1, srcComponent=191)
        sender = SwarmSender(0)
        frames = [f for step in range(30) for f in sender.frames(_report(0, step, 8), mav)]
        nodes.send(0, sim.sockets[0].local_port, frames)
        radio = sim.radio.stats
        carried = lambda: len(frames) - radio.dropped_for_bandwidth  # noqa: E731
        assert _until(
            nodes,
            lambda: (
                radio.frames_sent == len(frames) and nodes.receivers[1].stats.frames == carried()
            ),
            timeout_s=15.0,
        ), radio
        assert radio.dropped_for_bandwidth > 0
        assert 2 * sum(len(f) for f in frames) * 8 / 2000.0 > sim.config.step_s
        assert radio.delivered == 2 * carried()
        # what went fits the channel: its airtime ends within one period after the burst
        went = sum(sorted(len(f) for f in frames)[: carried()])
        assert went * 8 / 2000.0 <= sim.config.step_s + 2.0
    finally:
        running.close()


def test_signed_frames_pass_whole_and_unsigned_ones_stay_on_the_ground(nodes3):
    key = mission_key()
    nodes = Nodes(3, key)
    try:
        running = _start(nodes, RadioOptions(), [(20, 20), (21, 20), (22, 20)], signing_key=key)
        sim = running.sim
        signed = ml.MAVLink(None, srcSystem=1, srcComponent=191)
        sign_outgoing(signed, key, link_id=1)
        plain = ml.MAVLink(None, srcSystem=1, srcComponent=191)
        report = _report(0, 1, looks=20)
        nodes.send(0, sim.sockets[0].local_port, SwarmSender(0).frames(report, plain))
        signed_frames = SwarmSender(0, sequence=1).frames(report, signed)
        nodes.send(0, sim.sockets[0].local_port, signed_frames)
        assert _until(nodes, lambda: len(nodes.reports[1]) == len(nodes.reports[2]) == 1)
        assert nodes.reports[1] == nodes.reports[2] == [report]
        assert sim.radio.stats.frames_sent == len(signed_frames)  # the unsigned never went out
        assert sim.signature_check.unsigned_refused >= len(signed_frames)
        assert nodes.receivers[1].stats.unsigned_or_forged == 0
    finally:
        running.close()
        nodes.close()


def test_a_ground_station_hears_the_vehicles_in_its_range_and_changes_nothing_for_them(nodes3):
    """``--radio-ground-port``: a ground antenna at (22, 20) km with the radio's 10 km range
    hears vehicle 0 (2 km away) and not vehicle 2 (25 km away); the vehicles' own deliveries
    are those of a radio without it, and its count is in the summary."""
    nodes = nodes3
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as ground:
        ground.bind(("127.0.0.1", 0))
        ground.setblocking(False)
        running = _start(nodes, RadioOptions(range_km=10.0), [(20, 20), (27, 20), (45, 20)],
                         radio_ground_port=ground.getsockname()[1],
                         radio_ground_km=(22.0, 20.0))  # fmt: skip
        try:
            sim = running.sim
            near, far = SwarmSender(0), SwarmSender(2)
            mav = [ml.MAVLink(None, srcSystem=s, srcComponent=191) for s in (1, 3)]
            sent = [_report(0, step, looks=20) for step in range(1, 4)]
            frames = [f for r in sent for f in near.frames(r, mav[0])]
            nodes.send(0, sim.sockets[0].local_port, frames)
            far_frames = far.frames(_report(2, 1), mav[1])
            nodes.send(2, sim.sockets[2].local_port, far_frames)
            heard, parser, ear = [], ml.MAVLink(None), SwarmReassembler()

            def ground_heard() -> bool:
                nodes.pump()
                while True:
                    try:
                        data = ground.recv(65535)
                    except BlockingIOError:
                        break
                    for m in parser.parse_buffer(data) or []:
                        report = ear.accept_message(m, time.monotonic())
                        if report is not None:
                            heard.append(report)
                return len(heard) >= len(sent) and sim.radio.stats.frames_sent == (
                    len(frames) + len(far_frames))  # fmt: skip

            assert _until(nodes, ground_heard), sim.radio.summary()
            time.sleep(0.3)
            ground_heard()
            assert heard == sent  # vehicle 0's reports, whole and in order; none of vehicle 2's
            radio = sim.radio.stats
            assert nodes.reports[1] == sent and nodes.reports[2] == []
            # vehicle 1 heard vehicle 0 (and not 2); vehicle 2 heard nothing: as without a ground
            assert radio.delivered == len(frames)
            summary = sim.summary()["radio"]["ground"]
        finally:
            running.close()
    assert summary["delivered"] == len(frames) and summary["lost_to_range"] == len(far_frames)
    assert summary["bytes_received"] == sum(len(f) for f in frames)
    assert summary["position_km"] == [22.0, 20.0]


@pytest.mark.parametrize(
    "option, value, says",
    [
        ("--radio-loss", "1.5", "--radio-loss must be a probability in [0, 1]"),
        ("--radio-range-km", "0", "--radio-range-km must be a positive distance"),
        ("--radio-kbps", "-57.6", "--radio-kbps must be a positive rate"),
        ("--radio-latency-ms", "nan", "not a finite number"),
    ],
)
def test_bad_radio_options_get_one_line_and_exit_2(option, value, says):
    done = loopback.run_swarmplan(["sim", "--fast", "--duration-s", "1", option, value], 60)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and says in lines[0] and "Traceback" not in done.stderr


def test_sim_command_prints_the_radio_counters():
    port = loopback.free_udp_port()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sink:
        sink.bind(("127.0.0.1", port))
        done = loopback.run_swarmplan(
            ["sim", "--fast", "--duration-s", "5", "--gcs-port", str(port), "--quiet",
             "--radio-range-km", "20", "--radio-loss", "0.1", "--radio-kbps", "57.6",
             "--radio-latency-ms", "50"],
            60,
        )  # fmt: skip
    assert done.returncode == 0, done.stderr
    import json

    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert summary["radio"]["frames_sent"] == 0 and len(summary["radio"]["bytes_sent"]) == 10
