"""A node's own report that does not fit the swarm wire (a claim's cell off the area was one,
while claims' cells were unsigned: seen in a 250-step flown onboard mission, a claim at step
169, where the node died with a traceback and its plane was sent home; here a cell beyond i16)
is said in one line, counted in the node's link figures and not sent:
its neighbours take it as lost, as any frame the radio loses, and the node flies on. The vehicle
is a real loopback UDP peer; what does fit reaches it as TUNNEL frames."""

from __future__ import annotations

import socket
import time

from pymavlink.dialects.v20 import ardupilotmega as ml

from mavlink_bridge.mission.onboard_planner import OnboardPlanner
from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_wire.links import UdpInEndpoint
from planner.scenario import load_scenario
from planner.swarm_messages import CellClaim


def _node_beside_a_vehicle():
    scenario = load_scenario("paper-2uav")
    endpoint = UdpInEndpoint(spec="udpin:127.0.0.1:0", host="127.0.0.1", port=0).open()
    link = SwarmLink([endpoint])
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", 0))
    vehicle.settimeout(2.0)
    beat = ml.MAVLink_heartbeat_message(ml.MAV_TYPE_FIXED_WING, 3, 0, 0, 3, 3)
    vehicle.sendto(bytes(beat.pack(ml.MAVLink(None, 1, 1))), ("127.0.0.1", endpoint.port))
    deadline = time.monotonic() + 5
    while link.vehicle(1) is None and time.monotonic() < deadline:
        link.pump(0.05)
    assert link.vehicle(1) is not None
    said: list[str] = []
    starts = scenario.starts_for_seed(1)
    node = OnboardPlanner(scenario, [starts[0]], 1, uav=0, link=link,
                          period_wall_s=lambda: 1.0, say=said.append)  # fmt: skip
    return node, vehicle, said, endpoint


def _tunnels(vehicle: socket.socket) -> int:
    parser, count = ml.MAVLink(None), 0
    try:
        while True:
            data = vehicle.recv(4096)
            for msg in parser.parse_buffer(data) or []:
                count += msg.get_type() == "TUNNEL"
    except TimeoutError:
        return count


def test_a_report_beyond_the_wire_is_said_counted_and_not_sent():
    node, vehicle, said, endpoint = _node_beside_a_vehicle()
    vehicle.settimeout(0.5)
    try:
        bad = CellClaim(0, 3, (40_000, 4), 2, ((0, 4),), None)
        node._broadcast([bad])  # a cell the wire's i16 cannot hold: no exception
        assert node.stats.unsendable == 1 and node.stats.frames_sent == 0
        assert len(said) == 1 and said[0].startswith("warning: step 3: a report not sent")
        assert "(40000, 4)" in said[0]
        assert _tunnels(vehicle) == 0
        node._broadcast([CellClaim(0, 3, (1, 4), 2, ((0, 4),), None)])  # what fits goes out
        assert node.stats.frames_sent >= 1 and _tunnels(vehicle) == node.stats.frames_sent
        assert node.link_summary()["unsendable"] == 1
    finally:
        vehicle.close()
        endpoint.close()
