"""The planner of one UAV on board (``swarmplan node``): the daemon's planner for a fleet of one
vehicle. Each decision step it runs ``planner.uav_node.UavNode``'s exchanges over its vehicle's
link, as TUNNEL frames of the swarm link (``mavlink_wire.node_wire``, docs/onboard.md): the
autopilot (or the simulator's radio) carries them to the other planes' nodes in range.

A step, each phase ending as soon as what it waits for has arrived, or at its deadline (a share
of the decision period on the vehicles' clock, from the step's start):

1. ``begin``: its state, look, engagement outcome and threats are sent; it waits for the
   states of the neighbours heard at the last step (``STATES_SHARE``);
2. ``hear``: its track intent is sent; it waits for the intents of those it heard
   (``INTENTS_SHARE``);
3. ``rank``, then C_c by priority: it claims once every higher-priority flying neighbour's claim
   is in and final, or at the claim deadline (``CLAIMS_SHARE``), where ``UavNode.claim`` takes a
   move no unheard neighbour's reachable cell conflicts with, or holds. A request to a blocker
   to step aside waits for its answer until ``END_SHARE`` (unanswered: it holds and says so;
   answered: it says its claim is final). Until ``END_SHARE`` it answers the requests of
   lower-priority neighbours;
4. ``finish``: the decision for its UAV, and its neighbours' flights as heard
   (``heard_flights``): the decision step's flight envelope keeps its plane's predicted flight
   apart from theirs (``mavlink_bridge/safety/neighbour_flights.py``). Its state carries its
   plane's measured course and ground speed for theirs.

Messages of a later step (a neighbour whose look came first) wait for that step; those of an
earlier one are dropped. What the link carried, per step, is counted (:class:`NodeLinkStats`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mavlink_bridge.safety.neighbour_flights import HeardFlight
from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_wire.node_wire import NodeWire
from mavlink_wire.protocol import mavlink
from mavlink_wire.swarm_wire import FRAGMENT_HEADER, SwarmReassembler, SwarmSender, WireError
from planner.claim_deadline import PREDICT_STEPS
from planner.planner_interface import StepDecision
from planner.scenario import Scenario, UavStart
from planner.swarm_messages import CellClaim, Message, UavState
from planner.uav_node import UavNode

#: shares of a decision period (from the step's start) by which each phase gives up waiting
STATES_SHARE, INTENTS_SHARE, CLAIMS_SHARE, END_SHARE = 0.12, 0.2, 0.32, 0.4
POLL_S = 0.005
#: a resumed node believes a neighbour's step at most twice the outage and this many steps after
#: its checkpoint
REJOIN_AHEAD = 2


@dataclass
class NodeLinkStats:
    """What one node's swarm link carried, per decision step and in total."""

    bytes_sent: list[int] = field(default_factory=list)  # per step
    bytes_received: list[int] = field(default_factory=list)  # per step
    frames_sent: int = 0
    frames_received: int = 0
    reports_heard: int = 0
    messages_missed: int = 0  # gaps in a neighbour's message sequence (range or loss)
    late_messages: int = 0  # of a step already decided
    undecodable: int = 0  # reports that are no scenario's messages
    unsendable: int = 0  # own reports that did not fit the wire (said, not sent)
    neighbours_heard: list[int] = field(default_factory=list)  # per step: states heard
    phase_timeouts: dict[str, int] = field(default_factory=lambda: {
        "states": 0, "intents": 0, "claims": 0, "answers": 0})  # fmt: skip
    cpu_s: list[float] = field(default_factory=list)  # per step, this process
    steps_missed: int = 0  # a resumed node: steps the swarm decided while it was down
    wall_s: list[float] = field(default_factory=list)  # per step, begin to decision

    def summary(self, claims: Any, wire: Any) -> dict[str, Any]:
        sent, got = np.array(self.bytes_sent or [0]), np.array(self.bytes_received or [0])
        cpu = np.array(self.cpu_s or [0.0])
        return {
            "bytes_sent_per_step": {"mean": round(float(sent.mean()), 1), "max": int(sent.max())},
            "bytes_received_per_step": {
                "mean": round(float(got.mean()), 1),
                "max": int(got.max()),
            },  # fmt: skip
            "bytes_sent": self.bytes_sent,
            "bytes_received": self.bytes_received,
            "frames_sent": self.frames_sent,
            "frames_received": self.frames_received,
            "reports_heard": self.reports_heard,
            "messages_missed": self.messages_missed,
            "late_messages": self.late_messages,
            "undecodable": self.undecodable,
            "unsendable": self.unsendable,
            "neighbours_heard": self.neighbours_heard,
            "phase_timeouts": self.phase_timeouts,
            "claim_deadlines": dataclasses.asdict(claims),
            "wire": dataclasses.asdict(wire),
            "cpu_s_per_step": {
                "mean": round(float(cpu.mean()), 4),
                "max": round(float(cpu.max()), 4),
            },  # fmt: skip
            "wall_s_per_step": [round(w, 3) for w in self.wall_s],
            "steps_missed": self.steps_missed,
        }


class OnboardPlanner:
    """One UAV's planner over the swarm link (see the module docstring); built by the
    decision loop as ``factory(scenario, starts, seed)`` with the one vehicle's start."""

    algorithm = "hapf-aco-onboard"

    def __init__(
        self, scenario: Scenario, starts: Sequence[UavStart], seed: int, *, uav: int,
        link: SwarmLink | None, period_wall_s: Callable[[], float],
        say: Callable[[str], None] = lambda text: None,
    ) -> None:  # fmt: skip
        swarm = list(scenario.starts_for_seed(seed))
        swarm[uav] = starts[0]
        self.uav, self.size = uav, len(swarm)
        self._homes = [(float(s.x_km), float(s.y_km)) for s in swarm]  # (neighbour_flights)
        self.node = UavNode(scenario, swarm, seed, uav)
        self.link = link
        self.period_wall_s = period_wall_s
        self.say = say
        self.wire = NodeWire.for_scenario(scenario)
        self.sender = SwarmSender(uav)
        self.reassembler = SwarmReassembler(signature=None)  # (the link checked signatures)
        self.wire_stats = self.reassembler.stats  # (kept in a checkpoint; the buffers are not)
        self.stats = NodeLinkStats()
        self._ahead: list[Message] = []  # messages of a step not begun yet
        self._sequence: dict[int, int] = {}  # last message sequence heard of each neighbour
        #: each neighbour's latest step with its cell and claim heard: (step, cell, claim, heading)
        self._legs: dict[int, tuple[int, tuple[int, int], tuple[int, int], int]] = {}
        self._heard_flights: list[HeardFlight] = []  # of the step decided last
        self._claimed = False
        self._open = False  # between this step's begin and its decision
        self._sent = self._received = 0
        self.swarm_step = -1  # the newest step heard of a neighbour
        if link is not None:  # (None: the template a checkpoint is checked against)
            link.tunnel_listeners.append(self._heard)

    @property
    def beliefs(self) -> Any:
        """Its UAV's beliefs (the node's: one object, held once by a checkpoint)."""
        return self.node.beliefs

    @property
    def cfg(self) -> Any:
        return self.node.cfg

    @property
    def pheromone(self) -> Any:
        return self.node.planner.pheromone

    @property
    def grid(self) -> Any:
        return self.node.beliefs.grid

    @property
    def n(self) -> int:
        return self.node.beliefs.n

    # ------------------------------------------------------------------ a restart

    def hand_over(self, restored: OnboardPlanner) -> None:
        """A resumed node: give the planner restored from its checkpoint what is bound to this
        process, which a checkpoint leaves out (``checkpoint_codec.CACHES``): the link, with its
        listener moved over, the clock, where it says things, the wire's tables, fresh
        reassembly buffers counting on in the restored counters; and it listens afresh for the
        swarm's step."""
        restored.link, restored.period_wall_s = self.link, self.period_wall_s
        restored.say = self.say
        restored.wire, restored.reassembler = self.wire, self.reassembler
        self.reassembler.stats = restored.wire_stats
        restored._ahead, restored._heard_flights = [], []
        restored._legs = {}  # (not in a checkpoint: heard afresh from the next step)
        restored.swarm_step = -1
        restored.node.forget_step()
        if self.link is not None:
            if self._heard in self.link.tunnel_listeners:
                self.link.tunnel_listeners.remove(self._heard)
            self.link.tunnel_listeners.append(restored._heard)

    def rejoin(
        self, first_step: int, clock_step: Callable[[], int], steps: int, listen_s: float
    ) -> tuple[int, str]:
        """A resumed node: the step to carry on from, that of the swarm, and how it was found.
        It listens for up to ``listen_s`` wall seconds until a neighbour's report of
        ``first_step`` or later arrives: its step is the one the swarm is deciding (the node's
        newest look is of that instant too), unless it is implausibly far ahead of
        ``clock_step()``, the step of the mission's clock (the outage counted in decision
        periods): more than twice the outage plus :data:`REJOIN_AHEAD` steps after the
        checkpoint (a loaded simulator's clock runs in bursts). It takes the clock's step when
        none is heard (alone, or the others done) or the one heard is not plausible. The steps
        in between are not planned: its beliefs skip to that step (what is left of the mission
        counts from it)."""
        until = time.monotonic() + listen_s
        while self.swarm_step < first_step and time.monotonic() < until:
            self.link.pump(POLL_S)
        clock = clock_step()
        outage = clock - first_step + 1  # decision periods since the checkpoint, by the clock
        if first_step <= self.swarm_step <= first_step - 1 + 2 * outage + REJOIN_AHEAD:
            step, how = self.swarm_step, "heard of its neighbours"
        else:
            step, how = clock, "by the mission's clock"
        step = min(max(first_step, step), steps)
        self.beliefs.k += step - first_step
        self.stats.steps_missed += step - first_step
        return step, how

    # ------------------------------------------------------------------ the link

    def _broadcast(self, messages: Sequence[Message]) -> None:
        if not messages:
            return
        vehicle = self.link.vehicle(self.uav + 1)
        if vehicle is None:
            return
        report = self.wire.report(self.uav, messages[0].step, messages)
        try:
            frames = self.sender.messages(report)
        except WireError as exc:
            # never a crash mid-flight: the neighbours take it as lost (their claim deadline)
            self.stats.unsendable += 1
            self.say(f"warning: step {report.step}: a report not sent, {exc} ({report!r:.400})")
            return
        for msg in frames:
            vehicle.link.mav.send(msg)
            self._sent += len(msg.get_msgbuf())
            self.stats.frames_sent += 1

    def _heard(self, msg: mavlink.MAVLink_message) -> None:
        """A TUNNEL frame from the link: reassembled, decoded, taken in (or kept for later)."""
        self.stats.frames_received += 1
        self._received += len(msg.get_msgbuf())
        report = self.reassembler.accept_message(msg, time.monotonic())
        if report is None:
            return
        self._count_gap(msg)
        self.stats.reports_heard += 1
        try:
            messages = self.wire.messages(report)
        except WireError:
            self.stats.undecodable += 1
            return
        for m in messages:
            self._take(m)

    def _count_gap(self, msg: mavlink.MAVLink_message) -> None:
        header = bytes(int(b) & 0xFF for b in msg.payload[: FRAGMENT_HEADER.size])
        _, sender, sequence, *_ = FRAGMENT_HEADER.unpack(header)
        last = self._sequence.get(sender)
        if last is not None:
            self.stats.messages_missed += max(0, (sequence - last - 1) & 0xFFFF) if (
                (sequence - last) & 0xFFFF) < 0x8000 else 0  # fmt: skip
        self._sequence[sender] = sequence

    def _take(self, m: Message) -> None:
        k = self.beliefs.k
        if m.uav == self.uav:
            return
        self.swarm_step = max(self.swarm_step, m.step)
        if m.step > k or (m.step == k and not self._open):  # (before its own begin: kept)
            self._ahead.append(m)
        elif m.step < k:
            self.stats.late_messages += 1
            if isinstance(m, UavState):  # (expected at the next step: heard again in time)
                self.node.hear_late(m)
        elif isinstance(m, CellClaim) and m.displace is not None and m.displace[0] == self.uav:
            self.node.receive(m)
            if self._claimed:
                self._broadcast(self.node.answer(m))
        else:
            self.node.receive(m)

    def _wait(self, done: Callable[[], bool], until: float, phase: str) -> None:
        while not done():
            left = until - time.monotonic()
            if left <= 0:
                self.stats.phase_timeouts[phase] += 1
                return
            self.link.pump(min(POLL_S, left))

    # ------------------------------------------------------------------ the step

    def step(
        self, cells: np.ndarray, headings: np.ndarray, reports: Sequence[Any],
        engagements: Sequence[Any] | None = None, active: np.ndarray | None = None,
        positions_km: np.ndarray | None = None,
    ) -> StepDecision:  # fmt: skip
        t0, cpu0 = time.monotonic(), time.process_time()
        period = self.period_wall_s()
        node, inbox = self.node, lambda: self.node.inbox
        k = self.beliefs.k
        before = {j for j, s in node.last_heard.items() if s.step == k - 1 and j != self.uav}
        expected = before if k > 0 else set(range(self.size)) - {self.uav}
        self._sent = self._received = 0
        self._claimed = False
        outcome = None if engagements is None else engagements[0]
        flying = True if active is None else bool(np.asarray(active)[0])
        where = None if positions_km is None else np.asarray(positions_km)[0]
        said = node.begin(np.asarray(cells)[0], int(np.asarray(headings)[0]), reports[0],
                          outcome, flying, where)  # fmt: skip
        self._broadcast([self._with_flight(m) for m in said])
        self._open = True
        ahead, self._ahead = self._ahead, []
        for m in ahead:
            self._take(m)
        self._wait(lambda: expected <= set(inbox().states), t0 + STATES_SHARE * period, "states")
        self.stats.neighbours_heard.append(len(inbox().states) - 1)
        self._broadcast(node.hear())
        heard = set(inbox().states) - {self.uav}
        self._wait(lambda: heard <= set(inbox().tracks), t0 + INTENTS_SHARE * period, "intents")
        node.rank()
        self._claim(t0, period)
        decision = node.finish()
        self._open = False
        self._heard_flights = self._flights(k)
        self._note_legs(k)
        self._account(t0, cpu0)
        return decision

    # ------------------------------------------------------------------ the neighbours' flights

    def _with_flight(self, message: Message) -> Message:
        """Its state with its plane's measured course and ground speed (what its neighbours'
        flight envelopes predict its flight from); other messages as they are."""
        vehicle = None if self.link is None else self.link.vehicle(self.uav + 1)
        if not isinstance(message, UavState) or vehicle is None or vehicle.speed_mps <= 1.0:
            return message
        return dataclasses.replace(message, course_rad=float(vehicle.course_rad),
                                   speed_mps=float(vehicle.speed_mps))  # fmt: skip

    def _note_legs(self, k: int) -> None:
        """Each neighbour's cell and claim of step ``k`` (heard): the target it flies to until
        its next one, and its claim, should nothing newer be heard."""
        box = self.node.inbox
        for j, state in box.states.items():
            claim = box.claims.get(j)
            if j != self.uav and claim is not None:
                self._legs[j] = (k, state.cell, claim.cell, claim.heading)

    def _flights(self, k: int) -> list[HeardFlight]:
        """What it heard of each neighbour's flight for step ``k``
        (``neighbour_flights.HeardFlight``), from its latest state heard, at most
        ``PREDICT_STEPS`` old: this step's claim, or that step's when older, and the leg it
        flew from the step before."""
        out = []
        for j, state in self.node.last_heard.items():
            age = k - state.step
            if j == self.uav or not 0 <= age <= PREDICT_STEPS:
                continue
            leg = self._legs.get(j)
            claim = self.node.inbox.claims.get(j) if age == 0 else None
            if age > 0 and leg is not None and leg[0] == state.step:
                claim = CellClaim(j, state.step, leg[2], leg[3], ())
            flown = (leg[1], leg[2]) if age == 0 and leg is not None and leg[0] == k - 1 else None
            out.append(HeardFlight(
                j, age, state.position_km, state.course_rad, state.speed_mps, state.cell,
                state.heading, state.flying, None if claim is None else claim.cell,
                0 if claim is None else claim.heading, flown, self._homes[j],
            ))  # fmt: skip
        return out

    def heard_flights(self) -> list[HeardFlight]:
        """Its neighbours' flights as heard for the step it decided last (the decision step's
        flight envelope keeps its plane's flight apart from them: ``neighbour_flights.py``)."""
        return list(getattr(self, "_heard_flights", []))

    def _flying_neighbours(self, before: bool) -> set[int]:
        """Neighbours heard flying this step that claim before (``before``) or after this one."""
        box, mine = self.node.inbox, self.node.priority
        out = set()
        for j, intent in box.tracks.items():
            state = box.states.get(j)
            if j == self.uav or (state is not None and not state.flying):
                continue
            if (intent.priority < mine) == before:
                out.add(j)
        return out

    def _final(self, js: set[int]) -> bool:
        claims = self.node.inbox.claims
        return all(j in claims and claims[j].displace is None for j in js)

    def _claim(self, t0: float, period: float) -> None:
        """C_c: wait for the higher-priority claims, claim, settle a request to step aside,
        answer the lower-priority neighbours' requests until the end of the claim window."""
        node = self.node
        first = self._flying_neighbours(before=True)
        self._wait(lambda: self._final(first), t0 + CLAIMS_SHARE * period, "claims")
        claims = node.claim()
        self._claimed = True
        self._broadcast(claims)
        for claim in claims:
            if not isinstance(claim, CellClaim) or claim.displace is None:
                continue
            blocker = claim.displace[0]
            asked = claim.displace[1]
            answered = self._answered(blocker, asked, t0 + END_SHARE * period)
            node.displaced(answered)
            if answered:
                self._broadcast([dataclasses.replace(claim, displace=None)])
            else:
                self._broadcast([node.hold_claim()])
        after = self._flying_neighbours(before=False)
        self._wait(lambda: self._final(after), t0 + END_SHARE * period, "answers")

    def _answered(self, blocker: int, asked: tuple[int, int], until: float) -> bool:
        def moved() -> bool:
            claim = self.node.inbox.claims.get(blocker)
            return claim is not None and tuple(claim.cell) == tuple(asked)

        self._wait(moved, until, "answers")
        return moved()

    def _account(self, t0: float, cpu0: float) -> None:
        s = self.stats
        s.bytes_sent.append(self._sent)
        s.bytes_received.append(self._received)
        s.cpu_s.append(time.process_time() - cpu0)
        s.wall_s.append(time.monotonic() - t0)

    def link_summary(self) -> dict[str, Any]:
        """The link's figures for the node's result (``link``)."""
        return self.stats.summary(self.node.stats, self.wire_stats)
