"""The planner's swarm messages on the wire (mavlink_wire/node_wire.py): every message the nodes
of a paper-10uav swarm send comes back from its signed TUNNEL frames as itself, and a node swarm
whose every message goes through the wire decides what the swarm on the in-process bus decides;
the bytes a UAV sends per step stay inside the radio budget."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import dataclasses  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402

from mavlink_wire.node_wire import NodeWire  # noqa: E402
from mavlink_wire.signing import SignatureCheck, mission_key, sign_outgoing  # noqa: E402
from mavlink_wire.swarm_wire import SwarmReassembler, SwarmSender, WireError  # noqa: E402
from planner.registry import register  # noqa: E402
from planner.scenario import load_scenario  # noqa: E402
from planner.swarm_bus import NodeSwarmPlanner, SwarmBus  # noqa: E402
from planner.swarm_messages import Look, UavState  # noqa: E402
from sim_gateway.offline_runner import run_offline  # noqa: E402

BUDGET_BYTES = 3600  # 57.6 kbit/s shared by 20 UAVs at 10 s steps


class WireBus(SwarmBus):
    """The in-process bus, but every broadcast goes through signed TUNNEL frames and back."""

    wire: NodeWire
    key = mission_key()
    sent_bytes: dict[tuple[int, int], int]  # (uav, step) -> bytes on the radio

    def send(self, sender, messages, positions_km):
        if not messages:
            return super().send(sender, messages, positions_km)
        step = messages[0].step
        report = self.wire.report(sender, step, messages)
        mav = ml.MAVLink(None, srcSystem=sender + 1, srcComponent=191)
        sign_outgoing(mav, self.key, link_id=sender)
        frames = SwarmSender(sender).frames(report, mav)
        key = (sender, step)
        self.sent_bytes[key] = self.sent_bytes.get(key, 0) + sum(len(f) for f in frames)
        receiver = SwarmReassembler(signature=SignatureCheck(self.key))
        parser = ml.MAVLink(None)
        got = [receiver.accept_message(parser.decode(bytearray(f)), 0.0) for f in frames]
        heard = self.wire.messages(got[-1])
        assert [_metres(m) for m in heard] == [_metres(m) for m in messages]
        return super().send(sender, heard, positions_km)


def _metres(message):
    """Positions travel in whole metres."""
    if isinstance(message, UavState):
        x, y = message.position_km
        return dataclasses.replace(message, position_km=(round(x, 3), round(y, 3)))
    return message


built: list[NodeSwarmPlanner] = []


def _wire_nodes(scenario_, starts, seed):
    planner = NodeSwarmPlanner(scenario_, starts, seed)
    bus = WireBus(planner.bus.nodes, planner.bus.link)
    bus.wire = NodeWire.for_scenario(scenario_)
    bus.sent_bytes = {}
    planner.bus = bus
    built.append(planner)
    return planner


def test_a_swarm_through_the_wire_decides_what_the_bus_decides():
    register("nodes-through-wire", _wire_nodes)
    scenario = load_scenario("paper-10uav")
    register("nodes-plain", NodeSwarmPlanner)
    plain = run_offline(scenario, 1, 20, "nodes-plain", account=False)
    wired = run_offline(scenario, 1, 20, "nodes-through-wire", account=False)
    assert [u["track_km"] for u in wired["uavs"]] == [u["track_km"] for u in plain["uavs"]]
    assert wired["engagements"] == plain["engagements"]
    assert wired["decision_modes"] == plain["decision_modes"]
    sizes = np.array(list(built[-1].bus.sent_bytes.values()))
    assert sizes.max() <= BUDGET_BYTES  # signed, every exchange of the step
    print(f"bytes per UAV per step: mean {sizes.mean():.0f}, max {sizes.max()}")


def test_a_look_cut_by_the_area_edge_comes_back_with_its_cells_in_order():
    scenario = load_scenario("paper-10uav")
    wire = NodeWire.for_scenario(scenario)
    corner = np.array([0, 1]) + wire.offsets
    cells = corner[wire.grid.inside(corner)]
    look = Look(
        2, 9, tuple(map(tuple, cells.tolist())), tuple(bool(k % 3 == 0) for k in range(len(cells)))
    )
    assert wire.messages(wire.report(2, 9, [look])) == [look]
    with pytest.raises(WireError):
        wire.report(
            2, 9, [dataclasses.replace(look, cells=look.cells[1:], detected=look.detected[1:])]
        )


def test_a_claim_off_the_area_travels_as_it_was_made():
    """A UAV with no allowed move at the area's edge claims its ranking's first cell, which may
    lie off the area: seen flown, `CellClaim` (-1, 45) with no alternatives, which unsigned cells
    could not carry (the node stopped, later said it and sent nothing). Signed cells carry it,
    and a step-aside request's cell with it, through signed TUNNEL frames and back."""
    from planner.swarm_messages import CellClaim

    wire = NodeWire.for_scenario(load_scenario("paper-10uav"))
    key = mission_key()
    claims = [
        CellClaim(5, 184, (-1, 45), 3, (), None),
        CellClaim(2, 7, (0, 99), 1, ((-1, 98), (0, 98)), (4, (-1, 97))),
    ]
    for claim in claims:
        mav = ml.MAVLink(None, srcSystem=claim.uav + 1, srcComponent=191)
        sign_outgoing(mav, key, link_id=claim.uav)
        frames = SwarmSender(claim.uav).frames(wire.report(claim.uav, claim.step, [claim]), mav)
        receiver, parser = SwarmReassembler(signature=SignatureCheck(key)), ml.MAVLink(None)
        got = [receiver.accept_message(parser.decode(bytearray(f)), 0.0) for f in frames][-1]
        assert wire.messages(got) == [claim]
