"""The swarm link's byte budget (docs/onboard.md, "Byte budget"): what a report costs on the
radio, and the largest report a node of a scenario can send."""

from __future__ import annotations

import math

from mavlink_wire.protocol import mavlink
from mavlink_wire.swarm_wire import (
    Claim,
    Engagement,
    Look,
    NodeState,
    SwarmReport,
    SwarmSender,
    ThreatReport,
)


def wire_bytes(report: SwarmReport, signed: bool) -> int:
    """Bytes on the radio of ``report``: its TUNNEL frames as MAVLink 2 packs them."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
    if signed:
        mav.signing.secret_key = bytes(32)
        mav.signing.sign_outgoing = True
    return sum(len(f) for f in SwarmSender(report.uav).frames(report, mav))


def worst_case_report(
    uavs: int, footprint_cells: int, targets: int, threats: int, looks: int = 1
) -> SwarmReport:
    """The largest report a node of a swarm of ``uavs`` sends in one step: its state, ``looks``
    looks with every footprint bit set (1: its own; ``uavs``: relaying every other's too), one
    engagement outcome, every target serviced, one claim, every threat, all with values that
    MAVLink 2 cannot trim."""
    cell = (0xFFFF, 0xFFFF)
    return SwarmReport(
        uav=uavs - 1,
        step=0xFFFF,
        state=NodeState(cell, 7, 999.999, 999.999, 50.0, True, math.radians(359.99), 655.35),
        looks=tuple(Look(k % 256, 0xFFFF, cell, (True,) * footprint_cells) for k in range(looks)),
        engagements=(Engagement(0xFFFF, cell, 0xFFFF, True),),
        serviced=tuple(range(1, targets + 1)),
        claims=(Claim(cell, 255),),
        threats=(ThreatReport(999.999, 999.999, 99.999),) * threats,
    )
