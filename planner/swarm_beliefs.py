"""The swarm's beliefs and the paper's shared building blocks, one object for every UAV of the
swarm (batched): what each UAV knows and how it learns it, and the constraints every planner's
moves obey. HAPF-ACO (``planner.hapf_aco``), PSO (``planner.pso``) and ACOAPF
(``planner.acoapf``) are built on it, and so can a planner of one's own
(``planner.planner_interface``, docs/architecture.md).

Each UAV keeps its own beliefs (TPM, coverage it knows of, the threats and the swarm members it
has heard of); only the states and looks of the neighbours inside its cooperative radius reach
it. Per decision step a planner calls:

1. ``observe``: topology (eqs 1-3) and what each UAV hears (``planner.swarm_hearing``);
   engagement outcomes and serviced targets; probe update of the TPMs with own and
   neighbours' looks (eqs 17-18), renormalised (eq 16); the engagement choice (section
   3.2.1: the cell each UAV goes for, circled for more looks from ``pursue_threshold``, flown
   to and engaged from ``confirm_threshold``; higher value first; one UAV per target). It
   returns what the step's decision needs (``Hearing``);
2. its own decision, with ``move_options`` (C_m, C_t, C_r over the candidate cells,
   ``planner.feasibility``), ``update_return`` / ``return_scores`` (C_r's return home),
   ``claim`` (C_c) and ``engage_requests``;
3. ``finish_step``: the read-only observers, then the forecast of the TPMs to the next step
   (eqs 19-22).

| here | paper |
|---|---|
| ``radius_km`` | r_i, the cooperative radius (eqs 1-3) |
| ``tpm`` | the target probability maps p_mn (eqs 8-22) |
| ``coverage`` | the cells each UAV knows as searched (J_E, eq 6) |
| ``distance_km`` | L_past, the distance flown (C_r) |
| ``known_threats`` | the threats each UAV has found or heard of (C_t) |
| ``stall_steps`` | steps without a coverage gain, against N_t (escape) |

Nothing here does I/O and nothing here draws random numbers: randomness is the decision's.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from planner.config import PlannerConfig
from planner.constraints import SafetyModel, SafetyModels
from planner.engagement import EngagementOutcome
from planner.feasibility import MoveOptions, feasible_moves
from planner.grid import Grid, disc_overlap, disc_overlap_at, heading_of_angle, steps_to_reach
from planner.planner_interface import MODES, StepDecision
from planner.scenario import Scenario, UavStart
from planner.sensor_model import SensorReport
from planner.swarm_hearing import HeardSwarm, Hearing, SwarmHearing
from planner.target_probability_map import TargetProbabilityMaps
from planner.transition import claim_cells, range_scores


class SwarmBeliefs(SwarmHearing):
    """Every UAV's beliefs, batched, and the constraints shared by the planners (what they
    hear: ``planner.swarm_hearing.SwarmHearing``)."""

    def __init__(
        self, scenario: Scenario, starts: Sequence[UavStart], owners: Sequence[int] | None = None
    ) -> None:
        """``starts``: every member of the swarm; ``owners``: the members whose beliefs are
        kept here (all by default: the batched swarm; one: a UAV's own node,
        ``planner.uav_node``)."""
        cfg = scenario.config
        self.cfg: PlannerConfig = cfg
        self.scenario = scenario
        self.grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
        self.size = len(starts)  # N, the swarm's members
        self.owners = np.arange(self.size) if owners is None else np.asarray(owners, np.int64)
        n = len(self.owners)
        self.n = n
        xy = np.array([[s.x_km, s.y_km] for s in starts], dtype=float)
        self.member_home = self.grid.cell_of(xy)
        member_headings = heading_of_angle(np.radians([s.heading_deg for s in starts]))
        self.home = self.member_home[self.owners]
        self.home_flat = self.grid.flat(self.home)
        self.homes_key = tuple(int(h) for h in self.home_flat)
        self.cells = self.home.copy()
        self.headings = member_headings[self.owners]
        self.distance_km = np.zeros(n)
        self.done = np.zeros(n, dtype=bool)
        self.flying = ~self.done  # this step's: reachable and not done (``begin_step``)
        self.returning = np.zeros(n, dtype=bool)
        self.radius_km = np.full(n, min(cfg.coop_radius_init_km, cfg.sensing_radius_km))
        # What owner i last heard of member j (eqs 30-31): cell, heading, step.
        self.info_cells = np.repeat(self.member_home[None, :, :], n, axis=0)
        self.info_headings = np.repeat(member_headings[None, :], n, axis=0)
        self.info_step = np.full((n, self.size), -(10**9))
        self.info_step[np.arange(n), self.owners] = 0
        self.threat_xy = np.array([[t.x_km, t.y_km] for t in scenario.threats], float).reshape(
            -1, 2
        )
        self.threat_r = np.array([t.radius_km for t in scenario.threats], float)
        self.known_threats = np.full((n, len(self.threat_r)), scenario.threats_known)
        self.tpm = TargetProbabilityMaps(scenario.targets, cfg, n)
        self.coverage = np.zeros((n, cfg.grid_nx, cfg.grid_ny), dtype=bool)
        self.coverage_count = np.zeros(n, dtype=np.int64)
        self.stall_steps = np.zeros(n, dtype=np.int64)
        self.escape_goal = np.full((n, 2), -1, dtype=np.int64)
        self.track = np.full((n, 2), -1, dtype=np.int64)  # the cell each UAV goes for, or -1
        # ... and whether a target is confirmed there
        self.track_confirmed = np.zeros(n, dtype=bool)
        self.track_age = np.zeros(n, dtype=np.int64)  # steps on the current track so far
        self.target_ids = np.array([t.id for t in scenario.targets], dtype=np.int64)
        self.known_engaged = np.zeros((n, len(self.target_ids)), dtype=bool)
        self.engaged_applied = self.known_engaged.copy()  # removed from that UAV's TPM already
        self.engaged_cells = np.full((len(self.target_ids), 2), -1, dtype=np.int64)
        # where each UAV last asked for an engagement: its outcome comes with the next step,
        # when the UAV has moved on, and belongs to this cell
        self.request_cells = np.full((self.n, 2), -1, dtype=np.int64)
        self.measured_km: np.ndarray | None = None  # (N, 2) this step's measured positions
        self.footprint = self.grid.disc_offsets(cfg.detection_radius_km)
        self.track_window = self.grid.disc_offsets(2.0 * cfg.cell_km)
        self.pursuit_reach = int(np.ceil(cfg.pursue_range_km / cfg.cell_km)) + 2
        self.pursuit_steps = steps_to_reach(cfg.max_turn_deg, self.pursuit_reach)
        self.engage_cells, self.engage_fractions = disc_overlap(cfg.engage_radius_km, cfg.cell_km)
        self.k = 0
        self.mission_steps = scenario.steps  # the last step, for ``home_by_end``
        self._safety = SafetyModels(self._new_safety_model)  # by the known-threat row
        self._options: MoveOptions | None = None  # this step's, once the threats are heard
        #: Read-only observers, called as ``observe(beliefs, decision)`` after each decision and
        #: before the forecast (``planner.pursuit_log.PursuitLog``); they must not change state.
        self.observers: list[Callable[[SwarmBeliefs, StepDecision], None]] = []

    def safety_model(self, known: np.ndarray) -> SafetyModel:
        """C_t's model of the threats ``known`` (a row of ``known_threats``), cached."""
        return self._safety.get(known, self.k)

    def _new_safety_model(
        self, known: np.ndarray, searched: dict[int, float] | None
    ) -> SafetyModel:
        return SafetyModel(
            self.grid, self.threat_xy[known], self.threat_r[known], self.cfg.threat_margin_km,
            self.cfg.max_turn_deg, self.cfg.home_path_margin_km, searched,
            len(set(self.homes_key)),
        )  # fmt: skip

    def share_safety_models(self, other: SwarmBeliefs) -> None:
        """Use ``other``'s cache of C_t's models (beliefs of the same scenario: a model depends
        on the area, the threats known and the margins alone), so that planners of one swarm in
        one process build each model once."""
        self._safety = other._safety

    # ------------------------------------------------------------------ the step's beliefs

    def observe(
        self, cells: np.ndarray, headings: np.ndarray, reports: Sequence[SensorReport | None],
        engagements: Sequence[EngagementOutcome | None] | None,
        active: np.ndarray | None, positions_km: np.ndarray | None,
    ) -> Hearing:  # fmt: skip
        """Take in what the UAVs report at step k (the arguments of
        ``planner.planner_interface.SwarmPlanner.step``, for every member: the beliefs of the
        whole swarm): the three parts of the step's beliefs on the swarm's own rows."""
        size, own = self.size, self.owners
        active = np.ones(size, dtype=bool) if active is None else np.asarray(active, dtype=bool)
        cells = np.asarray(cells, dtype=np.int64).reshape(size, 2)[own]
        headings = np.asarray(headings, dtype=np.int64).reshape(size)[own]
        measured = None if positions_km is None else np.asarray(positions_km, float)[own]
        outcomes = None if engagements is None else [engagements[i] for i in own]
        self.begin_step(cells, headings, outcomes, active[own], measured)
        seen = self.hear(self.own_view(reports))
        self.leave_to_nearer(seen, self.cells, self.headings, self.track)
        return seen

    def own_view(self, reports: Sequence[SensorReport | None]) -> HeardSwarm:
        """The swarm as the owners are to each other: a batched swarm hears itself whole (its
        own rows are every member's, ``owners`` all)."""
        if self.n != self.size:
            raise ValueError("own_view needs the beliefs of every member (owners all)")
        return HeardSwarm(
            self.cells, self.headings, self.flying, np.ones(self.size, dtype=bool), reports,
            self.known_threats.copy(), self.known_engaged.copy(), self.engaged_cells,
        )  # fmt: skip

    def begin_step(
        self, cells: np.ndarray, headings: np.ndarray,
        engagements: Sequence[EngagementOutcome | None] | None,
        active: np.ndarray, positions_km: np.ndarray | None,
    ) -> None:  # fmt: skip
        """The step's first part, the owners' own (n rows): where they are, the threats they
        detect and their engagement outcomes. What they then tell the swarm is read from here
        (``planner.uav_node``)."""
        cfg = self.cfg
        self._options = None
        self.measured_km = positions_km
        cells = np.asarray(cells, dtype=np.int64).reshape(self.n, 2)
        moved = np.hypot(*((cells - self.cells) * cfg.cell_km).T)
        self.distance_km += np.where(active, moved, 0.0)
        self.cells = cells
        self.headings = np.asarray(headings, dtype=np.int64).reshape(self.n) % 8
        self.flying = active & ~self.done
        if len(self.threat_r):  # threats: detected within R + R_t
            seen = (
                distances_to_threats(self.grid.centre_km(cells), self.threat_xy)
                <= self.threat_r + cfg.detection_radius_km
            )
            self.known_threats |= seen & self.flying[:, None]
        self._take_engagements(engagements)

    def finish_step(self, decision: StepDecision) -> None:
        """The observers read the step's decision; then the forecast (eqs 19-22) to the next
        decision step."""
        for observe in self.observers:  # read-only (the target account's planner facts)
            observe(self, decision)
        self.tpm.forecast()
        self.k += 1
        self._options = None

    def _take_engagements(self, engagements: Sequence[EngagementOutcome | None] | None) -> None:
        """The owners' own engagement outcomes (one per owner, or None)."""
        if engagements is None:
            return
        for i, outcome in enumerate(engagements):
            if outcome is None:
                continue
            where = self.request_cells[i] if self.request_cells[i, 0] >= 0 else self.cells[i]
            if outcome.success:
                index = np.flatnonzero(self.target_ids == outcome.target_id)
                if index.size:
                    self.engaged_cells[index[0]] = where
                    self.known_engaged[i, index[0]] = True
            else:
                # nothing within the engage radius: a certain negative look at the cell of
                # the request
                self.tpm.apply_looks(
                    np.array([i]), [where[None, :]], [np.array([False])], where[None, :]
                )
            self.track[i] = -1

    def engage_probability(
        self, uavs: np.ndarray, cells: np.ndarray, within_km: np.ndarray | None = None
    ) -> np.ndarray:
        """Probability, as UAV ``uavs[m]`` believes, that a target lies within the engage radius
        of the centre of ``cells[m]``: ``1 - prod_cells (1 - p_cell * share of the cell inside
        the radius)``. A moving target's belief spreads over neighbouring cells, so this, not a
        single cell's p, is what confirms it and what an engagement needs. ``within_km`` (M, 2):
        around these points of the cells instead (km from their centres; a measured position)."""
        offsets, fractions = self.engage_cells, self.engage_fractions[None]
        if within_km is not None:
            half = self.cfg.cell_km / 2
            offsets, fractions = disc_overlap_at(
                np.clip(within_km, -half, half), self.cfg.engage_radius_km, self.cfg.cell_km
            )
        around = cells[:, None, :] + offsets[None]
        p = self.tpm.existence_at(np.asarray(uavs)[:, None], around) * fractions
        return 1.0 - np.prod(1.0 - p, axis=1)

    # ------------------------------------------------------------------ constraints

    def move_options(self) -> MoveOptions:
        """The candidate moves and the hard constraints on them (C_m, C_t, C_r), computed once
        a step after the threats are heard (a UAV's node reads them for its claim priority and
        for its decision)."""
        if self._options is None:
            steps_left = self.mission_steps - self.k - 1 if self.cfg.home_by_end else None
            self._options = feasible_moves(
                self.cells, self.headings, self.distance_km, self.homes_key, self.known_threats,
                self.safety_model, self.cfg, self.grid, steps_left,
            )  # fmt: skip
            self._safety.drop_unused(self.k)
        return self._options

    def update_return(self, opts: MoveOptions, flying: np.ndarray) -> None:
        """C_r: the return term takes over once the range slack is nearly spent (eqs 35/37,
        omega_2 = 1), or, when the scenario asks for the UAVs home by its last step
        (``home_by_end``), once the steps to spare are; a returning UAV back next to its start
        is done. Both are judged over the moves a UAV may take: one left with none (boxed in by
        a threat it found too close to turn away from) is not sent home for good, since the
        slack of no move says nothing of the way home."""
        cfg = self.cfg
        can_move = opts.feasible.any(axis=1) & flying
        bounded = np.isfinite(cfg.max_range_km)
        past_half = self.distance_km + opts.step_km.min(axis=1) > cfg.max_range_km / 2
        best_slack = np.where(opts.feasible, opts.slack_km, -np.inf).max(axis=1)
        self.returning |= bounded & past_half & (best_slack < cfg.return_margin_km) & can_move
        if cfg.home_by_end:
            best_time = np.where(opts.feasible, opts.time_slack, -np.inf).max(axis=1)
            self.returning |= (best_time < cfg.home_margin_steps) & can_move
        near_home = np.abs(self.cells - self.home).max(axis=1) <= 1
        self.done |= self.returning & near_home & flying

    @staticmethod
    def return_scores(
        scores: np.ndarray, modes: np.ndarray, opts: MoveOptions, returning: np.ndarray
    ) -> None:
        """C_r decides for the ``returning`` UAVs (``range_scores``), in place."""
        if returning.any():
            scores[returning] = range_scores(
                opts.home_km[returning], opts.feasible[returning], opts.time_slack[returning]
            )
            modes[returning] = MODES.index("return")

    def claim(
        self,
        ranked: np.ndarray,
        opts: MoveOptions,
        positions: np.ndarray,
        distances: np.ndarray,
        flying: np.ndarray,
    ) -> np.ndarray:
        """C_c for the whole swarm (owners all): the chosen candidate of every UAV
        (``claim_cells``) over the candidates ranked by ``claim_ranking``."""
        cfg = self.cfg
        ranked = self.claim_ranking(ranked, opts, distances, np.ones(self.size, dtype=bool))
        return claim_cells(
            ranked, opts.cells, opts.safe, positions, flying, cfg.cell_km,
            cfg.min_separation_km, cfg.separation_sense_km,
        )  # fmt: skip

    def claim_ranking(
        self, ranked: np.ndarray, opts: MoveOptions, distances: np.ndarray, received: np.ndarray
    ) -> np.ndarray:
        """The owners' candidates in the order they claim them, with one step of foresight:
        when another UAV (``received``) is within two closing steps, a move into a state with a
        single way on (``MoveOptions.freedom`` 1, e.g. between a threat and the area's edge)
        comes after every other allowed move, so two UAVs are not left one cell with no
        separated pair of moves. Separation comes before ``home_by_end``: when no move that
        keeps the time slack is separated, a safe move that spends it is taken (paper-10uav
        seed 4 met two UAVs in one cell at step 239 without this); forbidden moves last."""
        cfg, n = self.cfg, self.n
        gaps = np.where(received[None, :], distances, np.inf)
        gaps[np.arange(n), self.owners] = np.inf
        crowded = (gaps <= cfg.separation_sense_km + 2 * np.sqrt(2) * cfg.cell_km).any(axis=1)
        rows = np.arange(n)[:, None]
        cornered = (opts.freedom[rows, ranked] <= 1) & crowded[:, None]
        late = ~opts.feasible[rows, ranked]
        last = cornered.astype(np.int64) + 2 * late + 2 * ~opts.safe[rows, ranked]
        return np.take_along_axis(ranked, np.argsort(last, axis=1, kind="stable"), axis=1)

    def unsearched(self, cells: np.ndarray) -> np.ndarray:
        """(N, ...) bool: ``cells[i, ...]`` is inside the area and not yet covered as UAV i
        knows it."""
        covered = self.coverage.reshape(-1)  # (N * cells): UAV i's cell c at i * size + c
        own = (np.arange(self.n) * self.grid.size).reshape((-1,) + (1,) * (cells.ndim - 2))
        return ~covered[own + self.grid.clipped_flat(cells)] & self.grid.inside(cells)

    def engage_requests(self, engaging: np.ndarray) -> np.ndarray:
        """Engage once a target lies within the engage radius with probability at least
        ``confirm_threshold`` (``engage_probability`` at the UAV's own cell), whether or not the
        UAV was going for it: a UAV that finds itself on top of a confirmed target while
        searching or returning engages it on the way. A UAV whose measured position is known
        (``step``'s ``positions_km``) also needs that probability within the engage radius of
        where it is: a plane 0.4 km off its cell's centre does not reach the far side of the
        cell, and a request from there missed targets the cell's centre would have reached."""
        engage = engaging.copy()
        if engage.any():
            who = np.flatnonzero(engage)
            engage[who] = (
                self.engage_probability(who, self.cells[who]) >= self.cfg.confirm_threshold
            )
        if engage.any() and self.measured_km is not None:
            who = np.flatnonzero(engage)
            cells = self.cells[who]
            within = self.measured_km[who] - self.grid.centre_km(cells)
            engage[who] = self.engage_probability(who, cells, within) >= self.cfg.confirm_threshold
        self.request_cells[engage] = self.cells[engage]
        return engage


def distances_to_threats(positions_km: np.ndarray, threat_xy: np.ndarray) -> np.ndarray:
    diff = positions_km[:, None, :] - threat_xy[None, :, :]
    return np.hypot(diff[..., 0], diff[..., 1])
