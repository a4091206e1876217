"""HAPF-ACO (section 3.5, Fig. 2): one decision step for every UAV of the swarm.

The beliefs and the shared building blocks are ``planner.swarm_beliefs.SwarmBeliefs``
(topology, looks, TPMs, the engagement choice, the constraints); this module is HAPF-ACO's own
part of a step, after ``SwarmBeliefs.observe``:

4. pheromone: local decrement around predicted swarm positions, periodic global increment
   (eqs 28-34);
5. potential field at the UAV and over its sensor footprint (eqs 23-27);
6. transition: engage, return (C_r), escape after N_t steps without coverage gain, or the
   deterministic / heuristic rules (eqs 35-37, eta with a look-ahead corridor), all over the
   candidate cells allowed by C_m, C_t and C_r (``planner.feasibility``); then C_c by claiming
   cells in priority order, with one step of foresight;

and ``SwarmBeliefs.finish_step`` forecasts the TPMs to the next step (eqs 19-22).

| here | paper |
|---|---|
| ``pheromone`` | tau, the pheromone maps (eqs 28-34) |
| ``force_here``, ``force_max`` | F at the UAV and its largest over the footprint (eqs 23-27, 35) |
| ``eta`` | the heuristic information (eq 36) |
| ``q``, ``q1``, ``u`` | the random draws of the transition rules (eqs 35-37) |

Nothing here does I/O; randomness comes from one seeded generator.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from planner.belief_planner import BeliefPlanner
from planner.feasibility import MoveOptions
from planner.grid import HEADING_STEPS, corridor_offsets
from planner.pheromone import PheromoneMaps
from planner.planner_interface import MODES, StepDecision
from planner.potential_field import (
    attraction,
    block_masses,
    far_potential,
    far_weights,
    morse_repulsion,
    threat_repulsion,
)
from planner.scenario import Scenario, UavStart
from planner.swarm_beliefs import Hearing, SwarmBeliefs
from planner.target_probability_map import TargetProbabilityMaps
from planner.transition import (
    deterministic_scores,
    heuristic_choice,
    transition_weights,
    use_deterministic,
)


@dataclass(frozen=True)
class RankedMoves:
    """The owners' candidates as the transition rules rank them, before C_c."""

    ranked: np.ndarray  # (n, C) candidate indices, the rule's choice first
    options: MoveOptions  # the candidates and their constraints
    modes: np.ndarray  # (n,) index into MODES


class HapfAcoPlanner(BeliefPlanner):
    """The swarm's HAPF-ACO planners, batched (``planner.planner_interface.SwarmPlanner``)."""

    algorithm = "hapf-aco"

    def __init__(
        self,
        scenario: Scenario,
        starts: Sequence[UavStart],
        seed: int,
        owners: Sequence[int] | None = None,
    ) -> None:
        """``owners``: the UAVs this planner decides for (all by default; one in a UAV's own
        node, ``planner.uav_node``)."""
        self.beliefs = beliefs = SwarmBeliefs(scenario, starts, owners)
        cfg = self.cfg = beliefs.cfg
        self.grid = beliefs.grid
        n = self.n = beliefs.n
        # The swarm's random stream: every planner draws the whole swarm's numbers of a step and
        # uses its owners' (a UAV's own numbers, whoever decides for it)
        self.rng = np.random.default_rng([seed, 0xAC0])
        self.pheromone = PheromoneMaps(n, cfg)
        footprint = beliefs.footprint
        # a candidate is one cell away and the force needs one more cell around the footprint
        self.window_reach = int(np.abs(footprint).max()) + 1
        reach = np.arange(-self.window_reach, self.window_reach + 1)
        self.window_offsets = np.stack(np.meshgrid(reach, reach, indexing="ij"), axis=-1)
        self.centre_index = int(np.flatnonzero((footprint == 0).all(axis=1))[0])
        self.corridor, self.corridor_weights = corridor_offsets(
            footprint, cfg.eta_lookahead_steps, cfg.eta_lookahead_discount
        )
        # the far attraction's block weights, only when it is on (``far_weight`` > 0)
        self.far_kernel = (
            far_weights(
                cfg.grid_nx, cfg.grid_ny, cfg.cell_km, cfg.far_block_cells, cfg.far_length_km
            )
            if cfg.far_weight > 0
            else np.zeros((0, 0))
        )
        self.far_masses = np.zeros((n, self.far_kernel.shape[1]))

    @property
    def field_maps(self) -> TargetProbabilityMaps:
        """The TPM the potential field (eqs 23-24, the far attraction) and the heuristic
        information read: the beliefs' own, forecast included; where the beliefs keep a
        forecast-free twin (``static``: ACOAPF's ``ApfBeliefs``), that twin."""
        maps = self.beliefs.tpm
        return getattr(maps, "static", maps)

    def decide(self, seen: Hearing) -> StepDecision:
        """Steps 4-6: pheromone, then the potential field and the transition, with C_c's
        claims resolved among the owners (``SwarmBeliefs.claim``)."""
        ranking = self.rank_moves(seen)
        b = self.beliefs
        pick = b.claim(ranking.ranked, ranking.options, seen.positions, seen.distances, seen.flying)
        return self.finish_decision(ranking, pick, seen.flying)

    def rank_moves(self, seen: Hearing) -> RankedMoves:
        """Steps 4-6 up to C_c: pheromone, potential field, the transition rules' ranking."""
        self._update_pheromone(seen.flying)
        return self._rank(seen)

    def finish_decision(
        self, ranking: RankedMoves, pick: np.ndarray, flying: np.ndarray
    ) -> StepDecision:
        """The decision from the claimed candidates ``pick`` (n,): next cells, engagements."""
        b, modes = self.beliefs, ranking.modes.copy()
        cand, cand_head = ranking.options.cells, ranking.options.headings
        rows = np.arange(self.n)
        next_cells = np.where(flying[:, None], cand[rows, pick], b.cells)
        next_headings = np.where(flying, cand_head[rows, pick], b.headings)
        modes[~flying] = MODES.index("hold")
        engage = b.engage_requests(flying)
        return StepDecision(next_cells, next_headings, engage, b.done.copy(), modes)

    def _update_pheromone(self, flying: np.ndarray) -> None:
        cfg, b = self.cfg, self.beliefs
        age = b.k - b.info_step
        known = (age >= 0) & (age <= cfg.info_max_age_steps) & flying[:, None]  # (n, N)
        owners, members = np.nonzero(known)
        steps = HEADING_STEPS[b.info_headings[owners, members]] * age[owners, members][:, None]
        predicted = b.info_cells[owners, members] + steps  # eq 31, dead reckoning
        np.maximum(predicted, 0, out=predicted)  # clipped into the area
        np.minimum(predicted, (b.grid.nx - 1, b.grid.ny - 1), out=predicted)
        self.pheromone.local_update(owners, predicted)
        if b.k > 0 and b.k % cfg.global_update_period_steps == 0:
            self.pheromone.global_update()

    # ------------------------------------------------------------------ decision

    def _existence_window(self) -> np.ndarray:
        """Each UAV's existence probabilities on the square of half-side ``window_reach`` around
        its cell, (N, 2r+1, 2r+1) (0 outside the area): one TPM read serves the footprint's
        forces and every candidate's footprint mass."""
        around = self.beliefs.cells[:, None, None, :] + self.window_offsets[None]
        return self.field_maps.existence_at(np.arange(self.n)[:, None, None], around)

    def _forces(
        self, window: np.ndarray, positions: np.ndarray, neighbours: np.ndarray
    ) -> np.ndarray:
        """Total APF force (N, K, 2) at the footprint cells of each UAV (eqs 24, 25, 27), from its
        existence ``window`` (``_existence_window``)."""
        cfg, r, b = self.cfg, self.window_reach, self.beliefs
        patch = np.arange(-1, 2)
        ix = b.footprint[:, 0][:, None, None] + patch[None, :, None] + r  # (K, 3, 1)
        iy = b.footprint[:, 1][:, None, None] + patch[None, None, :] + r  # (K, 1, 3)
        existence = window[:, ix, iy]  # (N, K, 3, 3)
        centres = b.grid.centre_km(b.cells[:, None, :] + b.footprint[None, :, :])
        force = attraction(existence, cfg)
        force = force + threat_repulsion(
            centres, b.threat_xy, b.threat_r, b.known_threats, cfg
        )
        force = force + morse_repulsion(
            centres, positions, neighbours, cfg, self.grid.centre_km(b.cells)
        )
        return force

    def _pursuit_scores(
        self, cand: np.ndarray, cand_head: np.ndarray, moves: np.ndarray, feasible: np.ndarray
    ) -> np.ndarray:
        """Scores of the candidates for reaching each UAV's track cell: fewest turn-limited moves
        from the candidate (``steps_to_reach``), ties to the smaller angle; beyond the table's
        window, the angle to the cell (eq 35's deterministic rule)."""
        b = self.beliefs
        r = b.pursuit_reach
        offset = b.track[:, None, :] - cand  # (N, C, 2)
        near = (np.abs(offset) <= r).all(axis=2)
        ox = np.minimum(np.maximum(offset[..., 0] + r, 0), 2 * r)  # clipped into the table
        oy = np.minimum(np.maximum(offset[..., 1] + r, 0), 2 * r)
        steps = np.where(near, b.pursuit_steps[cand_head, ox, oy], 10**6).astype(float)
        angle = -deterministic_scores(
            moves, (b.track - b.cells).astype(float), np.ones_like(feasible)
        )
        # a suspect is circled (looked at from all sides, eq 35); a confirmed target is flown to
        steps = np.where(b.track_confirmed[:, None], steps, 0.0)
        return np.where(feasible, -steps - angle / (2 * np.pi), -np.inf)

    def _far_share(
        self, cand: np.ndarray, cand_head: np.ndarray, feasible: np.ndarray
    ) -> np.ndarray:
        """(N, C) in [0, 1]: the smoothed attraction field (``far_potential``) that each
        candidate's heading reaches ``far_lookahead_steps`` ahead, relative to the best allowed
        candidate: the pull toward distant probability mass (a prior's blob beyond the
        footprint)."""
        cfg, b = self.cfg, self.beliefs
        if b.k % cfg.far_refresh_steps == 0:
            maps = self.field_maps
            self.far_masses = block_masses(
                maps.maps, maps.scale, cfg.far_block_cells, ~b.coverage
            )
        ahead = cand + HEADING_STEPS[cand_head] * cfg.far_lookahead_steps
        v = far_potential(self.far_kernel, self.far_masses, b.grid.clipped_flat(ahead))
        high = np.where(feasible, v, -np.inf).max(axis=1, keepdims=True)
        return np.where(feasible & (high > 0), v / np.where(high > 0, high, 1.0), 0.0)

    def _eta(
        self, cand: np.ndarray, cand_head: np.ndarray, feasible: np.ndarray, window: np.ndarray
    ) -> np.ndarray:
        """The heuristic information eta (eq 36) of every candidate (N, C): the unsearched share
        of its footprint, of the corridor ahead of it, and its target probability mass
        (``window``: ``_existence_window``), plus the far attraction when it is on."""
        cfg, n, b = self.cfg, self.n, self.beliefs
        fp = cand[:, :, None, :] + b.footprint[None, None, :, :]  # (N, C, K, 2)
        new_share = b.unsearched(fp).sum(axis=2) / len(b.footprint)
        r = self.window_reach
        offset = (
            (cand - b.cells[:, None, :])[:, :, None, :] + b.footprint[None, None, :, :] + r
        )
        mass = window[np.arange(n)[:, None, None], offset[..., 0], offset[..., 1]].sum(
            axis=2
        )  # 0 outside
        mass_share = mass / np.maximum(mass.max(axis=1, keepdims=True), 1e-12)
        ahead = cand[:, :, None, :] + self.corridor[cand_head]  # (N, C, K', 2)
        ahead_unsearched = b.unsearched(ahead)
        corridor_w = self.corridor_weights[cand_head]
        ahead_share = (ahead_unsearched * corridor_w).sum(axis=2) / np.maximum(
            corridor_w.sum(axis=2), 1e-12
        )
        eta = (
            cfg.eta_floor
            + new_share
            + cfg.eta_lookahead_weight * ahead_share
            + cfg.eta_tpm_weight * mass_share
        )
        if cfg.far_weight > 0:
            eta = eta + cfg.far_weight * self._far_share(cand, cand_head, feasible)
        return eta

    def _escape_goals(self, flying: np.ndarray) -> np.ndarray:
        """The UAVs stalled N_t steps without a coverage gain (escape); each newly stalled one
        heads for the nearest cell it has not searched (``escape_goal``)."""
        b = self.beliefs
        stalled = (b.stall_steps >= self.cfg.escape_steps) & flying
        for i in np.flatnonzero(stalled & (b.escape_goal[:, 0] < 0)):
            _, (ix, iy) = ndimage.distance_transform_edt(b.coverage[i], return_indices=True)
            b.escape_goal[i] = (ix[tuple(b.cells[i])], iy[tuple(b.cells[i])])
        return stalled

    def _rank(self, seen: Hearing) -> RankedMoves:
        """Steps 5-6 for every owner, up to C_c."""
        cfg, n, b = self.cfg, self.n, self.beliefs
        flying, hears, positions = seen.flying, seen.hears, seen.positions
        near = (seen.distances <= cfg.separation_sense_km) & seen.received[None, :]
        opts = b.move_options()
        cand, cand_head, moves, feasible = opts.cells, opts.headings, opts.moves, opts.feasible
        b.update_return(opts, flying)

        # potential field at the UAV and over its footprint (eqs 23-27)
        points = b.cells[:, None, :] + b.footprint[None, :, :]
        window = self._existence_window()
        force = self._forces(window, positions, hears | near)
        norms = np.hypot(force[..., 0], force[..., 1])
        inside_fp = b.grid.inside(points)
        force_max = np.where(inside_fp, norms, 0.0).max(axis=1)
        force_here = force[:, self.centre_index]
        own, size = b.owners, b.size
        q = self.rng.random(size)[own]
        q1 = self.rng.random(size)[own]
        u = self.rng.random(size)[own]

        eta = self._eta(cand, cand_head, feasible, window)
        tau = self.pheromone.at(np.arange(n)[:, None], cand)
        weights = transition_weights(tau, eta, feasible, cfg)

        stalled = self._escape_goals(flying)
        modes = np.full(n, MODES.index("heuristic"))
        scores = np.where(feasible, np.log(np.maximum(weights, 1e-300)), -np.inf)
        choice = heuristic_choice(weights, q1, u, cfg)
        deterministic = use_deterministic(np.hypot(*force_here.T), force_max, q, cfg)
        det_scores = deterministic_scores(moves, force_here, feasible)
        scores = np.where(deterministic[:, None], det_scores, scores)
        modes[deterministic] = MODES.index("deterministic")
        escaping = stalled & (b.escape_goal[:, 0] >= 0) & ~deterministic
        if escaping.any():
            esc = deterministic_scores(
                moves, (b.escape_goal - b.cells).astype(float), feasible
            )
            scores = np.where(escaping[:, None], esc, scores)
            modes[escaping] = MODES.index("escape")
        engaging = (b.track[:, 0] >= 0) & flying
        if engaging.any():
            scores = np.where(
                engaging[:, None], self._pursuit_scores(cand, cand_head, moves, feasible), scores
            )
            modes[engaging] = MODES.index("engage")
        b.return_scores(scores, modes, opts, b.returning & flying)

        chosen_first = np.where(
            modes == MODES.index("heuristic"), choice, np.argmax(scores, axis=1)
        )
        # rank: the rule's choice first, then the others by score
        order = np.argsort(-np.where(np.isfinite(scores), scores, -1e300), axis=1, kind="stable")
        others = order[order != chosen_first[:, None]].reshape(n, -1)  # order is a permutation
        ranked = np.concatenate([chosen_first[:, None], others], axis=1)
        return RankedMoves(ranked, opts, modes)

