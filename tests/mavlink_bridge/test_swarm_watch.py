"""The coordinator's ear (``mavlink_bridge.mission.swarm_watch``) over real UDP on 127.0.0.1:
swarm-link TUNNEL frames sent to its port, as the simulator's ground radio passes them on, are
checked, decoded and shown. A step waits for every UAV heard at the step before, at most 1.5
decision periods; a UAV gone silent is shown where it was last heard, its link age growing,
inactive after three periods and named in the progress line; looks become coverage, an
engagement and a threat found become timeline events; unsigned frames are refused when the
mission signs. The clock is passed in, so nothing here waits on it."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import socket  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import loopback  # noqa: E402
import pytest  # noqa: E402

from mavlink_bridge.mission.swarm_watch import (  # noqa: E402
    GroundEar,
    HeardSwarm,
    SwarmWatch,
    progress_line,
)
from mavlink_wire.node_wire import NodeWire  # noqa: E402
from mavlink_wire.protocol import mavlink  # noqa: E402
from mavlink_wire.signing import mission_key, sign_outgoing  # noqa: E402
from mavlink_wire.swarm_wire import (  # noqa: E402
    Engagement,
    Look,
    NodeState,
    SwarmReport,
    SwarmSender,
    ThreatReport,
)
from planner.scenario import load_scenario  # noqa: E402

PERIOD_S = 1.0


@pytest.fixture
def scenario(tmp_path: Path):
    text = (Path(loopback.REPO) / "planner/scenarios/paper-10uav.toml").read_text()
    path = tmp_path / "paper-2uav-watch.toml"
    path.write_text(text.replace("count = 10", "count = 2"))
    return load_scenario(path)


class Swarm:
    """Two nodes' senders and a socket that sends their frames to the ear's port."""

    def __init__(self, scenario, ear: GroundEar, key: bytes | None = None) -> None:
        self.wire = NodeWire.for_scenario(scenario)
        self.ear = ear
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.senders = [SwarmSender(i) for i in range(2)]
        self.mavs = [mavlink.MAVLink(None, srcSystem=i + 1, srcComponent=191) for i in range(2)]
        if key is not None:
            for i, mav in enumerate(self.mavs):
                sign_outgoing(mav, key, link_id=i + 1)

    def report(self, uav: int, step: int, x_km: float, y_km: float, **parts) -> SwarmReport:
        cell = (int(x_km), int(y_km))
        bits = (False,) * len(self.wire.offsets)
        state = NodeState(cell, 2, x_km, y_km, 5.0)
        return SwarmReport(uav, step, state, (Look(uav, step, cell, bits),), **parts)

    def send(self, report: SwarmReport) -> None:
        for frame in self.senders[report.uav].frames(report, self.mavs[report.uav]):
            self.sock.sendto(frame, ("127.0.0.1", self.ear.port))

    def close(self) -> None:
        self.sock.close()


def _hear(watch: SwarmWatch, reports: int) -> None:
    """Pump until ``reports`` reports in all were taken (bounded)."""
    deadline = time.monotonic() + 10
    while watch.swarm.reports < reports:
        assert time.monotonic() < deadline, watch.ear.reassembler.stats
        watch.pump(0.1)


def test_steps_silence_coverage_and_events_as_heard(scenario):
    ear = GroundEar(None)
    swarm = HeardSwarm(scenario, seed=1, period_s=PERIOD_S, signed=False)
    shown = []
    watch = SwarmWatch(ear, swarm, lambda view, beliefs: shown.append((view, beliefs)))
    nodes = Swarm(scenario, ear)
    try:
        nodes.send(nodes.report(0, 0, 20.5, 30.5))
        nodes.send(nodes.report(1, 0, 60.5, 40.5))
        _hear(watch, 2)
        assert [v.step for v, _ in shown] == [0]  # both heard at it: shown at once
        view, beliefs = shown[0]
        assert [(v.x_km, v.y_km) for v in view.vehicles] == [(20.5, 30.5), (60.5, 40.5)]
        assert view.coverage > 0 and beliefs.coverage[0].any() and beliefs.coverage[1].any()
        covered = view.coverage

        # step 1: UAV 1 silent from now on; UAV 0 engaged a target and found a threat
        threat = scenario.threats[0]
        target = scenario.targets[0].id
        nodes.send(nodes.report(0, 1, 21.5, 30.5,
                                engagements=(Engagement(target, (21, 30), 1, True),),
                                threats=(ThreatReport(threat.x_km, threat.y_km,
                                                      threat.radius_km),)))  # fmt: skip
        _hear(watch, 3)
        heard_at = swarm.uavs[1].heard_s
        assert [v.step for v, _ in shown] == [0]  # UAV 1 is waited for...
        now = time.monotonic()
        assert swarm.due_steps(now + 1.4 * PERIOD_S) == []  # ...up to 1.5 periods
        later = heard_at + 1.6 * PERIOD_S
        assert swarm.due_steps(later) == [1]
        view = swarm.view(1, later)
        still = view.vehicles[1]
        assert (still.x_km, still.y_km) == (60.5, 40.5)  # where it was last heard
        assert still.last_heard_s == pytest.approx(1.6 * PERIOD_S) and still.active
        assert view.vehicles[0].x_km == 21.5 and view.coverage > covered
        assert view.engaged == 1 and view.engaged_value == scenario.targets[0].value
        kinds = {e.kind: e for e in view.events}
        assert kinds["engagement"].uav == 0 and f"target {target}" in kinds["engagement"].text
        assert kinds["threat"].x_km == threat.x_km and kinds["threat"].uav == 0

        # three periods of silence: inactive, named in the progress line
        gone = heard_at + 3.5 * PERIOD_S
        assert not swarm.vehicle_view(1, 1, gone).active
        assert swarm.vehicle_view(1, 1, gone).last_heard_s == pytest.approx(3.5 * PERIOD_S)
        line = progress_line(swarm, 10, 2, gone)
        assert line.startswith("coordinator: step 1/10 heard (1 of 2 UAVs at it)")
        assert "not heard: " in line and "UAV 1 4 s" in line and "engaged 1" in line
        # step 2 of UAV 0 alone: UAV 1 was not heard at step 1, so it is not waited for
        nodes.send(nodes.report(0, 2, 22.5, 30.5))
        _hear(watch, 4)
        assert swarm.shown == 2
    finally:
        nodes.close()
        ear.close()


def test_a_signing_mission_hears_only_signed_frames(scenario):
    key = mission_key()
    ear = GroundEar(key)
    swarm = HeardSwarm(scenario, seed=1, period_s=PERIOD_S, signed=True)
    watch = SwarmWatch(ear, swarm)
    plain, signed = Swarm(scenario, ear), Swarm(scenario, ear, key)
    try:
        plain.send(plain.report(0, 0, 20.5, 30.5))
        signed.send(signed.report(1, 0, 60.5, 40.5))
        _hear(watch, 1)
        time.sleep(0.2)
        watch.pump(0.1)
        assert swarm.reports == 1 and swarm.uavs[0].heard_s is None
        assert swarm.uavs[1].states[0].position_km == (60.5, 40.5)
        assert ear.endpoint.signature_check.unsigned_refused > 0
        assert swarm.vehicle_view(1, 0, time.monotonic()).signed is True
    finally:
        plain.close()
        signed.close()
        ear.close()
