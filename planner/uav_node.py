"""The planner of one UAV in a swarm without a centre (section 3.3.1): its own beliefs (TPM
layers, pheromone, the coverage and threats it knows of, what it last heard of each neighbour),
the messages it heard (``planner.swarm_messages``), and its own move, decided by the same
HAPF-ACO code as the batched swarm (``planner.hapf_aco.HapfAcoPlanner`` with one owner).

A step is driven from outside (``planner.swarm_bus.SwarmBus``, or a radio): ``begin`` (own
state, look, engagement outcome, threats: sent), ``hear`` (what arrived: sent back the track
intent), ``rank`` (the transition rules up to C_c), ``claim`` in C_c's priority order and
``finish``. C_c without a centre: a node claims after the claims of the higher-priority
neighbours that could conflict; one whose claim has not arrived by the node's turn (the
deadline) may make any move it can (``planner.claim_deadline.neighbour_moves``, holding
included), and the node keeps clear of all of them, holds where none can reach, or takes the
choice that keeps the most separation (``planner.claim_deadline.choose_under_deadline``,
counted in ``ClaimStats``). So does a node that heard a request to step aside but not how it
ended: the blocker may be at either cell, the asker at its claim or holding (``_unsettled``),
and, at the end of the claim window, a node that took the cell of a lower-priority neighbour
whose claim it never heard (``_recheck``): that neighbour may have missed this node's claim
and held.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from planner.claim_deadline import PREDICT_STEPS, choose_under_deadline, neighbour_moves
from planner.engagement import EngagementOutcome
from planner.hapf_aco import HapfAcoPlanner, RankedMoves
from planner.planner_interface import MODES, StepDecision
from planner.scenario import Scenario, UavStart
from planner.sensor_model import SensorReport
from planner.swarm_beliefs import HeardSwarm, Hearing
from planner.swarm_messages import (
    CellClaim,
    Engagements,
    Look,
    Message,
    ThreatsFound,
    TrackIntent,
    UavState,
)
from planner.transition import ClaimBoard, claim_board, claim_next, claim_priority


@dataclass
class ClaimStats:
    """C_c without a centre, counted over a mission."""

    # steps with neighbours' claims not heard by the deadline that could conflict, or with a
    # request to step aside whose end (the blocker's new claim, the asker's last) was not heard;
    # or where the node took the cell of a lower-priority neighbour whose claim it had not
    # heard by the end of the claim window (``UavNode._recheck``)
    missed: int = 0
    avoided: int = 0  # ... where the node took a move none of their moves comes near
    held: int = 0  # ... where it held a cell none of their moves comes near
    squeezed: int = 0  # ... where neither was left: the choice keeping the most separation
    swaps: int = 0  # a blocker asked to step aside, and it did
    swaps_failed: int = 0  # ... no answer by the deadline: the node held


@dataclass
class _Inbox:
    states: dict[int, UavState] = field(default_factory=dict)
    looks: dict[int, Look] = field(default_factory=dict)
    engagements: dict[int, Engagements] = field(default_factory=dict)
    threats: dict[int, ThreatsFound] = field(default_factory=dict)
    tracks: dict[int, TrackIntent] = field(default_factory=dict)
    claims: dict[int, CellClaim] = field(default_factory=dict)
    requests: dict[int, tuple[int, tuple[int, int]]] = field(default_factory=dict)  # to step aside


class UavNode:
    """One UAV's planner (see the module's docstring)."""

    def __init__(
        self, scenario: Scenario, starts: Sequence[UavStart], seed: int, uav: int
    ) -> None:
        self.uav = uav
        self.size = len(starts)
        self.planner = HapfAcoPlanner(scenario, starts, seed, owners=[uav])
        self.stats = ClaimStats()
        self._target_index = {int(t): i for i, t in enumerate(self.beliefs.target_ids)}
        self.inbox = _Inbox()
        self.last_heard: dict[int, UavState] = {}  # each neighbour's latest state
        self._report: SensorReport | None = None
        self._seen: Hearing | None = None
        self._ranking: RankedMoves | None = None
        self._board: ClaimBoard | None = None
        self._hold = False

    @property
    def beliefs(self):
        """Its planner's beliefs (one object: a checkpoint holds it once)."""
        return self.planner.beliefs

    @property
    def cfg(self):
        return self.planner.cfg

    def forget_step(self) -> None:
        """Drop what only one step's exchanges use (what it heard, ranked, claimed): a node
        resumed from a checkpoint (which does not hold them) starts its next step with
        ``begin``."""
        self.inbox = _Inbox()
        self._report = self._seen = self._ranking = self._board = None
        self._hold = False

    # ------------------------------------------------------------------ exchange 1

    def begin(
        self, cell: np.ndarray, heading: int, report: SensorReport | None,
        outcome: EngagementOutcome | None, active: bool = True,
        position_km: np.ndarray | None = None,
    ) -> list[Message]:  # fmt: skip
        """The step's own part; returns what the UAV tells the swarm."""
        b, k = self.beliefs, self.beliefs.k
        self.inbox = _Inbox()
        request = tuple(int(v) for v in b.request_cells[0])
        measured = None if position_km is None else np.asarray(position_km, float)[None, :]
        b.begin_step(np.asarray(cell).reshape(1, 2), np.array([heading]), [outcome],
                     np.array([active]), measured)  # fmt: skip
        self._report = report
        here = tuple(int(v) for v in b.cells[0])
        where = measured[0] if measured is not None else b.grid.centre_km(b.cells)[0]
        state = UavState(self.uav, k, here, int(b.headings[0]), (float(where[0]), float(where[1])),
                         float(b.radius_km[0]), bool(b.flying[0]))  # fmt: skip
        own = None
        if outcome is not None:
            at = request if request[0] >= 0 else here
            own = (int(outcome.target_id), int(outcome.success), at)
        serviced = tuple(
            (int(b.target_ids[t]), (int(b.engaged_cells[t, 0]), int(b.engaged_cells[t, 1])))
            for t in np.flatnonzero(b.known_engaged[0])
        )
        sent: list[Message] = [state, Engagements(self.uav, k, own, serviced)]
        sent.append(ThreatsFound(self.uav, k, tuple(np.flatnonzero(b.known_threats[0]).tolist())))
        if report is not None and len(report.cells) > 0:
            cells = tuple((int(x), int(y)) for x, y in np.asarray(report.cells))
            sent.append(Look(self.uav, k, cells, tuple(bool(d) for d in report.detected)))
        for message in sent:
            self.receive(message)
        return sent

    def hear_late(self, state: UavState) -> None:
        """A neighbour's state of a step already decided (it came late: a neighbour that came
        back into range, or restarted and caught up): not used for that step, but it is where
        the neighbour was last, newer than what was heard before, so the node expects it at the
        next step and predicts its moves from there."""
        held = self.last_heard.get(state.uav)
        if state.uav != self.uav and (held is None or held.step < state.step):
            self.last_heard[state.uav] = state

    def receive(self, message: Message) -> None:
        """Take in one message heard (any exchange); one of another step is ignored."""
        if message.step != self.beliefs.k:
            return
        box = {
            UavState: self.inbox.states, Look: self.inbox.looks,
            Engagements: self.inbox.engagements, ThreatsFound: self.inbox.threats,
            TrackIntent: self.inbox.tracks, CellClaim: self.inbox.claims,
        }[type(message)]  # fmt: skip
        box[message.uav] = message
        if isinstance(message, UavState):
            self.last_heard[message.uav] = message
        if isinstance(message, CellClaim) and message.displace is not None:
            self.inbox.requests[message.uav] = message.displace
        if isinstance(message, CellClaim) and self._board is not None:
            self._take_claim(message)

    # ------------------------------------------------------------------ exchange 2

    def hear(self) -> list[Message]:
        """What the UAV heard of the swarm; returns its track intent and C_c priority."""
        b = self.beliefs
        self._seen = b.hear(self._view())
        safe = int(b.move_options().safe.sum())
        track = tuple(int(v) for v in b.track[0])
        intent = TrackIntent(self.uav, b.k, track, claim_priority(safe, self.uav, self.size))
        self.receive(intent)
        return [intent]

    def _view(self) -> HeardSwarm:
        b, box, size = self.beliefs, self.inbox, self.size
        cells = np.zeros((size, 2), dtype=np.int64)
        headings = np.zeros(size, dtype=np.int64)
        flying = np.zeros(size, dtype=bool)
        received = np.zeros(size, dtype=bool)
        for j, s in box.states.items():
            cells[j], headings[j], flying[j], received[j] = s.cell, s.heading, s.flying, True
        reports: list[SensorReport | None] = [None] * size
        for j, look in box.looks.items():
            reports[j] = SensorReport(np.array(look.cells, dtype=np.int64).reshape(-1, 2),
                                      np.array(look.detected, dtype=bool))  # fmt: skip
        reports[self.uav] = self._report
        threats = np.zeros((size, len(b.threat_r)), dtype=bool)
        for j, found in box.threats.items():
            threats[j, list(found.threats)] = True
        engaged = np.zeros((size, len(b.target_ids)), dtype=bool)
        cells_of = np.full((len(b.target_ids), 2), -1, dtype=np.int64)
        index = self._target_index
        for j, heard in sorted(box.engagements.items()):
            for target, where in heard.serviced:
                t = index.get(target)
                if t is not None:
                    engaged[j, t] = True
                    if cells_of[t, 0] < 0:
                        cells_of[t] = where
        return HeardSwarm(cells, headings, flying, received, reports, threats, engaged, cells_of)

    # ------------------------------------------------------------------ exchange 3

    def rank(self) -> None:
        """One UAV per target, then the transition rules up to C_c."""
        b, seen = self.beliefs, self._seen
        assert seen is not None
        tracks = np.full((self.size, 2), -1, dtype=np.int64)
        for j, intent in self.inbox.tracks.items():
            tracks[j] = intent.track
        view_cells = np.zeros((self.size, 2), dtype=np.int64)
        view_headings = np.zeros(self.size, dtype=np.int64)
        for j, s in self.inbox.states.items():
            view_cells[j], view_headings[j] = s.cell, s.heading
        b.leave_to_nearer(seen, view_cells, view_headings, tracks)
        ranking = self.planner.rank_moves(seen)
        ranked = b.claim_ranking(ranking.ranked, ranking.options, seen.distances, seen.received)
        self._ranking = RankedMoves(ranked, ranking.options, ranking.modes)
        self._board = self._new_board(seen)
        self._hold = False
        for claim in list(self.inbox.claims.values()):
            self._take_claim(claim)

    @property
    def priority(self) -> int:
        return self.inbox.tracks[self.uav].priority

    def _new_board(self, seen: Hearing) -> ClaimBoard:
        """The claims as this node will know them: its own candidates in row ``uav``."""
        assert self._ranking is not None
        size, opts, cfg = self.size, self._ranking.options, self.cfg
        c = opts.cells.shape[1]
        ranked = np.tile(np.arange(c), (size, 1))
        ranked[self.uav] = self._ranking.ranked[0]
        allowed = np.zeros((size, c), dtype=bool)
        allowed[self.uav] = opts.safe[0]
        candidates = np.zeros((size, c, 2), dtype=np.int64)
        candidates[self.uav] = opts.cells[0]
        positions = np.where(seen.received[:, None], seen.positions, np.nan)
        return claim_board(
            ranked, candidates, allowed, positions, seen.members_flying, cfg.cell_km,
            cfg.min_separation_km, cfg.separation_sense_km,
        )  # fmt: skip

    def _take_claim(self, claim: CellClaim) -> None:
        """Write a neighbour's claim on the board (its alternatives as its candidates); a claim
        that asks this UAV to step aside is answered by moving, when the cell asked for keeps
        clear of every claim this node knows of."""
        board, j = self._board, claim.uav
        assert board is not None
        if j == self.uav:
            return
        cells = [claim.cell] + [a for a in claim.alternatives if a != claim.cell]
        c = board.spots.shape[1]
        cells = cells[:c] + [cells[0]] * (c - len(cells[:c]))
        board.spots[j] = (np.array(cells, dtype=float) + 0.5) * self.cfg.cell_km
        board.allowed[j] = [True] * min(len(claim.alternatives) + 1, c) + [False] * max(
            0, c - len(claim.alternatives) - 1
        )
        board.ranked[j] = np.arange(c)
        board.choice[j] = 0
        board.claimed[j] = board.spots[j, 0]
        if self._seen is not None and not self._seen.received[j]:
            # its state was lost, its claim came: the board cannot tell how far it is, so
            # the claim counts (the link's range is the only distance known)
            board.senses[self.uav, j] = True

    def claim(self) -> list[Message]:
        """This node's claim on its board (``planner.transition.claim_next``), after the
        claims it heard; when a higher-priority neighbour's claim is missing, or the end of a
        request to step aside is (``_unsettled``), by
        ``planner.claim_deadline.choose_under_deadline`` instead (no request to step aside)."""
        board, ranking = self._board, self._ranking
        assert board is not None and ranking is not None
        i, b = self.uav, self.beliefs
        if not b.flying[0]:
            return []
        missed, unsettled = self._missed_moves(), self._unsettled()
        if not len(missed) and not len(unsettled):
            moved = claim_next(i, board)
            displace = None
            if moved is not None:
                alt = board.spots[moved, board.choice[moved]] / self.cfg.cell_km - 0.5
                displace = (int(moved), (int(round(alt[0])), int(round(alt[1]))))
            return [self._claim_message(displace)]
        self._by_deadline(unsettled, missed)
        return [self._claim_message(None)]

    def _by_deadline(
        self, unsettled: np.ndarray, missed: np.ndarray, fallback: np.ndarray | None = None
    ) -> None:
        """This node's move or hold on its board by ``choose_under_deadline``: clear of the
        claims it heard and ``unsettled`` (points), and of the ``missed`` moves; when squeezed,
        clear of the ``fallback`` moves instead, if that leaves an option; counted."""
        board, b, i = self._board, self.beliefs, self.uav
        assert board is not None
        here = b.grid.centre_km(b.cells)[0]
        known = board.senses[i] & ~np.isnan(board.claimed[:, 0])  # claims sensed, holds
        heard = np.concatenate([board.claimed[known], unsettled])
        options = (here, board.spots[i], board.ranked[i], board.allowed[i], heard)
        choice = choose_under_deadline(*options, missed, board.limit)
        if choice.rule == "squeezed" and fallback is not None:
            second = choose_under_deadline(*options, fallback, board.limit)
            choice = second if second.rule != "squeezed" else choice
        self.stats.missed += 1
        setattr(self.stats, choice.rule, getattr(self.stats, choice.rule) + 1)
        if choice.hold:
            self._hold = True
            board.claimed[i] = here
        else:
            board.choice[i] = choice.candidate
            board.claimed[i] = board.spots[i, choice.candidate]

    def _unsettled(self) -> np.ndarray:
        """(U, 2) km: where a request to step aside that this node heard may have put the two
        UAVs it concerns, beyond their claims on the board, while the node has not heard how it
        ended: the claimant at its own cell until its final claim or its hold is heard (it holds
        when the blocker's answer does not reach it), and the blocker at the cell it was asked
        to take until its new claim there is heard (it stepped aside)."""
        points = []
        for asker, (blocker, cell) in self.inbox.requests.items():
            state = self.last_heard.get(asker)
            final = self.inbox.claims[asker].displace is None
            if asker != self.uav and not final and state is not None:
                points.append(state.cell)
            answer = self.inbox.claims.get(blocker)
            if blocker != self.uav and (answer is None or answer.cell != cell):
                points.append(cell)
        return (np.array(points, float).reshape(-1, 2) + 0.5) * self.cfg.cell_km

    def hold_claim(self) -> CellClaim:
        """The claim of this node holding its cell (a request to step aside unanswered)."""
        self._hold = True
        return self._claim_message(None)

    def _claim_message(self, displace: tuple[int, tuple[int, int]] | None) -> CellClaim:
        assert self._board is not None and self._ranking is not None
        b, opts, board = self.beliefs, self._ranking.options, self._board
        pick = int(board.choice[self.uav])
        if self._hold:
            cell, heading = tuple(int(v) for v in b.cells[0]), int(b.headings[0])
        else:
            cell = tuple(int(v) for v in opts.cells[0, pick])
            heading = int(opts.headings[0, pick])
        alternatives = tuple(
            tuple(int(v) for v in opts.cells[0, c])
            for c in board.ranked[self.uav] if opts.safe[0, c] and c != pick
        )
        return CellClaim(self.uav, b.k, cell, heading, alternatives, displace)  # type: ignore[arg-type]

    def _missed_moves(self) -> np.ndarray:
        """(M, 2, 2) km: every move (``neighbour_moves``) of each neighbour that should have
        claimed before this node and has not been heard to (its priority unknown counts as
        before), last heard at most ``PREDICT_STEPS`` ago, that comes near enough to matter."""
        mine, cfg = self.priority, self.cfg
        moves: list[np.ndarray] = []
        for j, state in self.last_heard.items():
            if j == self.uav or j in self.inbox.claims:
                continue
            intent = self.inbox.tracks.get(j)
            if intent is not None and intent.priority > mine:
                continue  # it claims after this node
            if not state.flying and state.step == self.beliefs.k:
                continue  # holding: on the board already
            age = self.beliefs.k - state.step
            if age > PREDICT_STEPS:
                continue
            moves.append(neighbour_moves(state.cell, state.heading, age, cfg.max_turn_deg,
                                         cfg.cell_km))  # fmt: skip
        if not moves:
            return np.zeros((0, 2, 2))
        near = np.concatenate(moves)
        here = self.beliefs.grid.centre_km(self.beliefs.cells)[0]
        reach = cfg.separation_sense_km + 2 * cfg.cell_km
        return near[(np.hypot(*(near[:, 1] - here).T) <= reach)
                    | (np.hypot(*(near[:, 0] - here).T) <= reach)]  # fmt: skip

    def _recheck(self) -> None:
        """At the end of the claim window: C_c lets this node claim the cell of a neighbour that
        claims after it, which is expected to move on (``claim_next``, as the central planner
        does). The neighbour may have missed this node's claim, though, and a node that missed
        it keeps clear of this node's every move, holding included, or holds when squeezed:
        two adjacent UAVs flying at each other met in one cell (paper-10uav seed 2 at 10 km,
        10 % loss, step 225, UAVs 0 and 6; seed 4 at 10 km, 30 %, UAVs 2 and 9; seed 9 at
        50 km, 30 %, UAVs 1 and 7: each time the lower-priority UAV had no option clear of the
        other's moves). So when such a neighbour's claim is to hold where it is (certain), or
        has not arrived by the end of the window, the node takes its move again by the deadline
        rule (``choose_under_deadline``), beside the claims it heard and the neighbours missed
        at its turn. A neighbour whose claim did not arrive counts as a missed claim: its
        moves, holding included. When no option is clear of them all, the node keeps clear of
        its hold alone (``fallback``): had the neighbour heard this node's claim it would move
        to a cell clear of it, often the node's own (seed 4 at 10 km, 30 %, step 227: a node
        that held there was run into), so the node moves on past it where it can. With every
        claim heard (a perfect link) this applies only to a neighbour that holds after its
        request to step aside went unanswered: the nodes still fly the central run's tracks
        (tests/planner/test_uav_nodes.py, seeds 1-3)."""
        board, cfg, i = self._board, self.cfg, self.uav
        assert board is not None
        if self._hold or not self.beliefs.flying[0]:
            return
        stuck, silent, holds = False, [], []
        for j, state in self.inbox.states.items():
            intent, claim = self.inbox.tracks.get(j), self.inbox.claims.get(j)
            if j == i or not state.flying or intent is None or intent.priority < self.priority:
                continue  # not flying, or its claim was awaited at this node's turn
            if claim is not None and tuple(claim.cell) != tuple(state.cell):
                continue  # it moves on
            there = (np.array(state.cell, float) + 0.5) * cfg.cell_km
            if np.hypot(*(there - board.claimed[i])) >= board.limit:
                continue
            stuck = True
            if claim is None:
                silent.append(neighbour_moves(state.cell, state.heading, 0, cfg.max_turn_deg,
                                              cfg.cell_km))  # fmt: skip
                holds.append(np.stack([there, there])[None])
        if stuck:
            missed = self._missed_moves()
            self._by_deadline(self._unsettled(), np.concatenate([missed, *silent]),
                              np.concatenate([missed, *holds]) if holds else None)  # fmt: skip

    def answer(self, claim: CellClaim) -> list[Message]:
        """A claim that asks this UAV to step aside: move, and say so, when the cell keeps clear
        of the claims this node knows of (``answered`` by its new claim)."""
        board = self._board
        if board is None or claim.displace is None or claim.displace[0] != self.uav:
            return []
        cell = claim.displace[1]
        opts = self._ranking.options if self._ranking is not None else None
        if opts is None or self._hold:
            return []
        found = [c for c in range(opts.cells.shape[1])
                 if tuple(opts.cells[0, c]) == cell and opts.safe[0, c]]  # fmt: skip
        if not found:
            return []
        spot = (np.array(cell, float) + 0.5) * self.cfg.cell_km
        others = board.claimed[board.senses[self.uav] & ~np.isnan(board.claimed[:, 0])]
        others = others[np.hypot(*(others - board.claimed[claim.uav]).T) > 1e-9] if len(
            others) else others  # fmt: skip
        asker = (np.array(claim.cell, float) + 0.5) * self.cfg.cell_km
        if len(others) and (np.hypot(*(others - spot).T) < board.limit).any():
            return []
        if np.hypot(*(asker - spot)) < board.limit:
            return []
        board.choice[self.uav] = found[0]
        board.claimed[self.uav] = spot
        return [self._claim_message(None)]

    def displaced(self, answered: bool) -> None:
        """The answer to this node's request to a blocker: none by the deadline, hold."""
        if answered:
            self.stats.swaps += 1
        else:
            self.stats.swaps_failed += 1
            self._hold = True

    # ------------------------------------------------------------------ the decision

    def finish(self) -> StepDecision:
        """The UAV's decision (one row, after ``_recheck``), then the forecast to the next
        step."""
        assert self._board is not None and self._ranking is not None and self._seen is not None
        self._recheck()
        pick = np.array([int(self._board.choice[self.uav])])
        decision = self.planner.finish_decision(self._ranking, pick, self._seen.flying)
        if self._hold and self._seen.flying[0]:
            b = self.beliefs
            decision.next_cells[0] = b.cells[0]
            decision.next_headings[0] = b.headings[0]
            decision.modes[0] = MODES.index("hold")
        self.beliefs.finish_step(decision)
        self._board = None
        return decision
