"""The coordinator's ear on the swarm link (docs/onboard.md, "The coordinator hears the swarm"):
a ground station that only listens to what the planner nodes broadcast each decision step and
turns it into the mission view (docs/view.md) and the coordinator's progress lines.

* :class:`GroundEar`: a UDP port (``udpin``, ``mavlink_wire.links``) where a ground radio passes
  on the TUNNEL frames it hears (in the simulator: ``swarmplan sim --radio-ground-port``,
  ``sim_gateway.radio.GroundRadio``); the frames are checked (MAVLink 2 signing, with the
  mission's key), reassembled and decoded by the swarm link's own receiver
  (``mavlink_wire.swarm_wire.SwarmReassembler``) and mapped to the planner's messages
  (``mavlink_wire.node_wire.NodeWire``), as a node does with what it hears.
* :class:`HeardSwarm`: what was heard: each UAV's state by step (cell, heading, measured
  position, flying), the cell it claimed next, its looks (as coverage, per UAV), engagement
  outcomes, threats found, and when it was last heard. A decision step is shown once every
  UAV heard at the step before was heard at it, or 1.5 decision periods after its first report
  (a UAV out of range or lost is then shown where it was last heard, its link age growing).

It sends nothing and commands nothing: killed or deaf, the nodes fly on.
"""

from __future__ import annotations

import select
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mavlink_wire.links import open_endpoint
from mavlink_wire.node_wire import NodeWire
from mavlink_wire.signing import SignatureCheck
from mavlink_wire.swarm_wire import SwarmReassembler, SwarmReport, WireError
from mission_view.view_model import StepView, TimelineEvent, VehicleView
from planner.belief_snapshot import CoverageBeliefs
from planner.scenario import Scenario
from planner.swarm_messages import CellClaim, Engagements, Look, ThreatsFound, UavState

#: states kept per UAV (by step): enough to show a step a few steps after it was heard
KEPT_STATES = 8
#: a UAV not heard for this many decision periods is shown inactive (its link age in the table)
SILENT_PERIODS = 3.0
#: a step is shown at the latest this many decision periods after its first report (each node
#: keeps its own vehicle's clock and a busy companion computer starts its step late)
SHOW_AFTER_PERIODS = 1.5


class GroundEar:
    """A UDP port on ``host`` (a free one) where the ground radio's frames arrive; ``hear``
    returns the swarm reports completed by what came in."""

    def __init__(self, signing_key: bytes | None, host: str = "127.0.0.1") -> None:
        self.endpoint = open_endpoint(f"udpin:{host}:0")
        if signing_key is not None:
            self.endpoint.signature_check = SignatureCheck(signing_key)
        self.reassembler = SwarmReassembler()
        self.frames = 0

    @property
    def port(self) -> int:
        return self.endpoint.port

    @property
    def signed(self) -> bool:
        return self.endpoint.signature_check is not None

    def hear(self, timeout_s: float) -> list[SwarmReport]:
        """Wait up to ``timeout_s`` for frames; the reports they complete."""
        sock = self.endpoint.sock
        if sock is None or not select.select([sock], [], [], max(0.0, timeout_s))[0]:
            return []
        reports = []
        now = time.monotonic()
        for msg, _ in self.endpoint.receive():
            self.frames += 1
            report = self.reassembler.accept_message(msg, now)
            if report is not None:
                reports.append(report)
        return reports

    def close(self) -> None:
        self.endpoint.close()


@dataclass
class HeardUav:
    """What the ground heard of one UAV."""

    states: dict[int, UavState] = field(default_factory=dict)  # by step, the newest few
    step: int = -1  # the newest step of a state heard
    heard_s: float | None = None  # wall clock of its last report
    claim: tuple[int, int] | None = None  # the cell it claimed for its next move
    look_step: int | None = None  # its newest look heard
    look_s: float | None = None
    threats: set[int] = field(default_factory=set)  # scenario indices it said it found

    def state_at(self, step: int) -> UavState | None:
        """Its state at ``step`` or, not heard then, the newest before (else the oldest kept)."""
        before = [k for k in self.states if k <= step]
        if before:
            return self.states[max(before)]
        return self.states[min(self.states)] if self.states else None

    @property
    def flying(self) -> bool:
        newest = self.states.get(self.step)
        return newest is None or newest.flying


class HeardSwarm:
    """The swarm as the ground heard it (see the module's docstring). ``period_s``: one
    decision period in wall seconds; ``signed``: the ground checks signatures."""

    def __init__(self, scenario: Scenario, seed: int, period_s: float, signed: bool) -> None:
        self.scenario = scenario
        self.wire = NodeWire.for_scenario(scenario)
        cfg = scenario.config
        self.n = scenario.uav_count
        self.period_s = period_s
        self.signed = signed
        self.coverage = np.zeros((self.n, cfg.grid_nx, cfg.grid_ny), dtype=bool)
        self.beliefs = CoverageBeliefs(self.coverage)  # the view's coverage layer
        starts = scenario.starts_for_seed(seed)
        self.homes = [(s.x_km, s.y_km, s.heading_deg) for s in starts]
        self.uavs = [HeardUav() for _ in range(self.n)]
        self.values = {t.id: t.value for t in scenario.targets}
        self.engaged: dict[int, tuple[int, int]] = {}  # target id -> (uav, step)
        self.events: list[TimelineEvent] = []  # not shown yet
        self.first_heard: dict[int, float] = {}  # step -> wall clock of its first state
        self.shown = -1  # the newest step shown
        self.started: float | None = None
        self.reports = 0
        self.undecodable = 0  # reports of a UAV out of range, or that do not map

    @property
    def newest_step(self) -> int:
        return max((u.step for u in self.uavs), default=-1)

    def take(self, report: SwarmReport, now: float) -> None:
        """One report heard at wall clock ``now``."""
        if not 0 <= report.uav < self.n:
            self.undecodable += 1
            return
        try:
            messages = self.wire.messages(report)
        except WireError:
            self.undecodable += 1
            return
        self.reports += 1
        uav = self.uavs[report.uav]
        uav.heard_s = now
        for m in messages:
            if isinstance(m, UavState):
                self._state(report.uav, m, now)
            elif isinstance(m, Look) and 0 <= m.uav < self.n and m.cells:
                cells = np.array(m.cells, dtype=np.int64)
                self.coverage[m.uav, cells[:, 0], cells[:, 1]] = True
                if uav.look_step is None or m.step >= uav.look_step:
                    uav.look_step, uav.look_s = m.step, now
            elif isinstance(m, Engagements) and m.outcome is not None:
                self._engagement(report.uav, m)
            elif isinstance(m, ThreatsFound):
                self._threats(report.uav, m)
            elif isinstance(m, CellClaim) and m.displace is None:
                uav.claim = m.cell

    def _state(self, i: int, m: UavState, now: float) -> None:
        uav = self.uavs[i]
        uav.states[m.step] = m
        for old in sorted(uav.states)[:-KEPT_STATES]:
            del uav.states[old]
        uav.step = max(uav.step, m.step)
        self.first_heard.setdefault(m.step, now)
        if self.started is None:
            self.started = now

    def _engagement(self, i: int, m: Engagements) -> None:
        target, success, _ = m.outcome  # type: ignore[misc]
        state = self.uavs[i].states.get(m.step)
        x, y = (None, None) if state is None else state.position_km
        if success and target not in self.engaged:
            self.engaged[target] = (i, m.step)
            text = f"engaged target {target} (value {self.values.get(target, 0):g})"
            self.events.append(TimelineEvent(m.step, "engagement", text, i, x, y))
        elif not success:
            self.events.append(TimelineEvent(m.step, "miss", "engagement: no target in reach",
                                             i, x, y))  # fmt: skip

    def _threats(self, i: int, m: ThreatsFound) -> None:
        uav = self.uavs[i]
        for t in sorted(set(m.threats) - uav.threats):
            threat = self.scenario.threats[t]
            known = any(t in other.threats for other in self.uavs)
            if not known:
                text = (f"threat found at ({threat.x_km:g}, {threat.y_km:g}) km, radius "
                        f"{threat.radius_km:g} km")  # fmt: skip
                self.events.append(TimelineEvent(m.step, "threat", text, i, threat.x_km,
                                                 threat.y_km))  # fmt: skip
            uav.threats.add(t)

    # ------------------------------------------------------------------ what is shown

    def due_steps(self, now: float, flush: bool = False) -> list[int]:
        """The steps to show now, in order: every UAV heard at the step before was heard at it, or
        ``SHOW_AFTER_PERIODS`` passed since its first report (``flush``: every step heard)."""
        due = []
        while self.shown < self.newest_step:
            k = self.shown + 1
            first = self.first_heard.get(k)
            # (a UAV not heard at the step before, silent or gone, is not waited for)
            waiting = any(u.step == k - 1 for u in self.uavs)
            late = first is not None and now - first >= SHOW_AFTER_PERIODS * self.period_s
            if waiting and not flush and first is not None and not late:
                break
            due.append(k)
            self.shown = k
        return due

    def view(self, step: int, now: float, truth: list[list[float]] | None = None) -> StepView:
        """Decision step ``step`` as heard, at wall clock ``now``."""
        events = [e for e in self.events if e.step <= step]
        self.events = [e for e in self.events if e.step > step]
        vehicles = [self.vehicle_view(i, step, now) for i in range(self.n)]
        engaged_value = sum(self.values.get(t, 0.0) for t in self.engaged)
        return StepView(
            step, vehicles, coverage=float(self.coverage.any(axis=0).mean()),
            engaged=len(self.engaged), engaged_value=float(engaged_value),
            wall_s=0.0 if self.started is None else now - self.started, truth=truth,
            events=events,
        )  # fmt: skip

    def vehicle_view(self, i: int, step: int, now: float) -> VehicleView:
        """UAV ``i`` at ``step``: where it said it was (its start before it was heard)."""
        uav, (hx, hy, heading_deg) = self.uavs[i], self.homes[i]
        state = uav.state_at(step)
        x, y = (hx, hy) if state is None else state.position_km
        silent = None if uav.heard_s is None else max(0.0, now - uav.heard_s)
        flying = state is None or state.flying
        target = None
        if uav.claim is not None and flying:
            cx, cy = self.wire.grid.centre_km(np.array([uav.claim]))[0]
            target = (float(cx), float(cy))
        return VehicleView(
            float(x), float(y), heading_deg if state is None else state.heading * 45.0,
            active=silent is not None and silent < SILENT_PERIODS * self.period_s and flying,
            target_km=target, last_heard_s=silent, signed=self.signed, done=not flying,
            home_km=(hx, hy), last_look=uav.look_step,
            last_look_s=None if uav.look_s is None else max(0.0, now - uav.look_s),
        )  # fmt: skip

    def silent(self, now: float) -> list[tuple[int, float | None]]:
        """UAVs not heard for more than one decision period: (uav, seconds; None: never)."""
        out = []
        for i, uav in enumerate(self.uavs):
            if uav.heard_s is None:
                out.append((i, None))
            elif now - uav.heard_s > self.period_s and uav.flying:
                out.append((i, now - uav.heard_s))
        return out


def progress_line(swarm: HeardSwarm, steps: int, running: int, now: float) -> str:
    """``coordinator: step K/N heard ...``: the newest step shown, the UAVs heard at it, the
    heard coverage and engagements, the silent UAVs and the node processes still running
    (before the first step: that it listens, while the nodes launch their planes)."""
    nodes = f"{running} node{'' if running == 1 else 's'} running"
    if swarm.shown < 0:
        heard = sum(u.heard_s is not None for u in swarm.uavs)
        return f"coordinator: listening to the swarm link ({heard} of {swarm.n} heard); {nodes}"
    k = swarm.shown
    at_k = sum(u.step >= k for u in swarm.uavs)
    silent = ", ".join(
        f"UAV {i} {'never heard' if s is None else f'{s:.0f} s'}" for i, s in swarm.silent(now)
    )
    return (
        f"coordinator: step {k}/{steps} heard ({at_k} of {swarm.n} UAVs at it), coverage "
        f"{swarm.coverage.any(axis=0).mean() * 100:.1f}% heard, engaged {len(swarm.engaged)}"
        f"{f'; not heard: {silent}' if silent else ''}; {nodes}"
    )


@dataclass
class SwarmWatch:
    """The coordinator's loop body: hear, take, show. ``post(view, beliefs)``: the view
    session's (None: no view); ``truth()``: the simulator's true targets, or None."""

    ear: GroundEar
    swarm: HeardSwarm
    post: Callable[[StepView, object], None] | None = None
    truth: Callable[[], list[list[float]] | None] | None = None

    def pump(self, timeout_s: float, flush: bool = False) -> list[int]:
        """Hear for up to ``timeout_s``; the steps shown (posted to the view) by it."""
        for report in self.ear.hear(timeout_s):
            self.swarm.take(report, time.monotonic())
        now = time.monotonic()
        due = self.swarm.due_steps(now, flush)
        for k in due:
            view = self.swarm.view(k, now, None if self.truth is None else self.truth())
            if self.post is not None:
                self.post(view, self.swarm.beliefs)
        return due
