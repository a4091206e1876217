"""PSO baseline: particle swarm optimisation of each UAV's short path (the paper's section 4.2,
Algorithm 1, "PSO ... applied in the mission planning problem [4]").

The paper gives no details of its PSO beyond "PSO is used to solve this search-attack problem".
We use the common receding-horizon form: every decision step, each UAV optimises a path of
``horizon_steps`` moves with a particle swarm and flies its first move.

- **Beliefs are HAPF-ACO's** (``planner.swarm_beliefs.SwarmBeliefs``): dynamic topology (eqs 1-3),
  TPM with probe and forecast updates (eqs 8-22), shared looks and coverage, target confirmation
  (section 3.2.1). Only the decision differs; PSO keeps no pheromone map (eqs 28-34) and uses no
  potential field (eqs 23-27).
- **Particles.** A particle is a vector of ``horizon_steps`` real turn commands in
  [-k - 1/2, k + 1/2] (k = phi_max / 45 deg); rounding gives the heading changes, so every
  decoded path obeys C_m. Standard inertia-weight PSO (Clerc-Kennedy constriction
  w = 0.7298, c1 = c2 = 1.49618) with a velocity clamp; particle 0 starts from last step's best
  path shifted by one move (warm start), particle 1 flies straight, the rest are random.
- **Fitness (eq 7 per UAV).** Search (omega = 0, J_E with the TPM): over the union of the sensor
  footprints along the path, the cells not yet known to be searched (and not inside the
  footprints of the paths neighbours announced at the last step) count 1 each, plus
  ``tpm_weight`` times the cell's target existence probability relative to the highest one
  near the UAV; plus a terminal value that pulls toward unsearched area and expected targets
  beyond the horizon (10 x 10-cell blocks weighted by exp(-distance / ``terminal_length_km``)).
  Attack (omega = 1, J_T): once a target is confirmed, the fitness is minus the closest
  approach of the path to it (earlier is better), so the swarm of particles plans the
  interception within the turn limit.
- **Constraints (eq 5), shared with HAPF-ACO.** Each path move must be allowed by
  ``planner.constraints.SafetyModel`` (C_t and the area, viable states) and keep the range slack
  ``L_max - L_past - path - D_left - reserve`` non-negative (C_r); a path is scored over its
  feasible prefix and penalised per infeasible move. The first move is chosen among the
  candidates ``planner.feasibility.feasible_moves`` allows, the return home follows the same
  rule as HAPF-ACO (``planner.transition.range_scores``) once the slack is spent, and C_c is
  resolved by ``SwarmBeliefs.claim`` (``planner.transition.claim_cells`` with foresight).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from planner.belief_planner import BeliefPlanner
from planner.feasibility import MoveOptions, threat_groups
from planner.grid import HEADING_LENGTHS, HEADING_STEPS, turn_options
from planner.planner_interface import MODES, StepDecision
from planner.scenario import Scenario, UavStart
from planner.swarm_beliefs import Hearing, SwarmBeliefs


def _clamp(a: np.ndarray, low: float, high: float) -> np.ndarray:
    """``np.clip`` without its per-call overhead (it dominates on these small arrays)."""
    return np.minimum(np.maximum(a, low), high)


@dataclass(frozen=True)
class PsoSettings:
    """Parameters of the PSO baseline (not in the paper; see docs/experiments.md)."""

    particles: int = 24  # particles per UAV
    iterations: int = 5  # PSO iterations per decision step (evaluations = particles x iterations)
    horizon_steps: int = 5  # moves per particle path
    inertia: float = 0.7298  # w, Clerc-Kennedy constriction
    cognitive: float = 1.49618  # c1, pull toward the particle's best
    social: float = 1.49618  # c2, pull toward the UAV's swarm best
    velocity_max: float = 1.0  # clamp, in turn units per iteration
    tpm_weight: float = 1.0  # weight of the (locally normalised) TPM against one unsearched cell
    terminal_weight: float = 3.0  # weight of the beyond-horizon value at the path's end
    terminal_length_km: float = 10.0  # decay length of the beyond-horizon value
    block_cells: int = 10  # block size of the beyond-horizon value
    block_refresh_steps: int = 5  # how often the block values are recomputed
    infeasible_penalty: float = 1000.0  # per move of a path that breaks a constraint


class PsoPlanner(BeliefPlanner):
    """Receding-horizon PSO over short paths, one particle swarm per UAV, batched over UAVs
    (``planner.planner_interface.SwarmPlanner``)."""

    algorithm = "pso"

    def __init__(
        self,
        scenario: Scenario,
        starts: Sequence[UavStart],
        seed: int,
        settings: PsoSettings | None = None,
    ) -> None:
        self.beliefs = SwarmBeliefs(scenario, starts)
        self.cfg, self.n, self.grid = self.beliefs.cfg, self.beliefs.n, self.beliefs.grid
        self.footprint = self.beliefs.footprint
        self.rng = np.random.default_rng([seed, 0xAC0])
        s = self.settings = settings or PsoSettings()
        if s.particles < 2 or s.iterations < 1 or s.horizon_steps < 1:
            raise ValueError("PSO needs at least 2 particles, 1 iteration and a 1-step horizon")
        self.max_turn = int(turn_options(self.cfg.max_turn_deg).max())
        h = s.horizon_steps
        self.plans = np.full((self.n, h, 2), -1, dtype=np.int64)  # best path of the last step
        self.plan_turns = np.zeros((self.n, h))
        self.plan_valid = np.zeros(self.n, dtype=bool)
        reach = int(np.abs(self.footprint).max())
        self.window = h + reach  # cells a path's footprints can touch, around the UAV
        side = 2 * self.window + 1
        dx, dy = np.meshgrid(
            np.arange(side) - self.window, np.arange(side) - self.window, indexing="ij"
        )
        self.window_offsets = np.stack([dx.ravel(), dy.ravel()], axis=1)
        self.footprint_flat = self.footprint[:, 0] * side + self.footprint[:, 1]
        ex, ey = np.meshgrid(np.arange(-h, h + 1), np.arange(-h, h + 1), indexing="ij")
        self.end_offsets = np.stack([ex.ravel(), ey.ravel()], axis=1)  # where a path can end
        b = s.block_cells
        bx, by = self.block_shape = (-(-self.grid.nx // b), -(-self.grid.ny // b))
        cx, cy = np.meshgrid(
            (np.arange(bx) + 0.5) * b - 0.5, (np.arange(by) + 0.5) * b - 0.5, indexing="ij"
        )
        self.block_centres = np.stack([cx.ravel(), cy.ravel()], axis=1)  # in cell units
        self.block_value = np.zeros((self.n, bx * by))
        cells = np.stack(
            np.meshgrid(np.arange(self.grid.nx), np.arange(self.grid.ny), indexing="ij"), -1
        )
        gap = cells.reshape(-1, 1, 2) - self.block_centres[None]  # (nx * ny, B, 2)
        distance_km = np.hypot(gap[..., 0], gap[..., 1]) * self.cfg.cell_km
        #: exp(-distance / terminal_length_km) from every cell to every block centre.
        self.block_weights = np.exp(-distance_km / s.terminal_length_km)
        self.block_step = np.full(self.n, -(10**9))


    # ------------------------------------------------------------------ decision

    def decide(self, seen: Hearing) -> StepDecision:
        """The receding-horizon PSO of every searching UAV, then HAPF-ACO's return, claim and
        engagement rules. PSO keeps no pheromone map (eqs 28-34 are HAPF-ACO's)."""
        n, b = self.n, self.beliefs
        flying, hears = seen.flying, seen.hears
        opts = b.move_options()
        b.update_return(opts, flying)  # C_r: the return rule of HAPF-ACO, unchanged

        returning = self.beliefs.returning & flying
        engaging = (self.beliefs.track[:, 0] >= 0) & flying & ~returning
        search = flying & ~returning
        scores = np.full(opts.feasible.shape, -np.inf)
        modes = np.full(n, MODES.index("heuristic"))
        modes[engaging] = MODES.index("engage")
        best_paths: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        if search.any():
            idx = np.flatnonzero(search)
            scores[idx], paths, turns = self._optimise(idx, engaging[idx], opts, hears)
            best_paths = {int(i): (paths[a], turns[a]) for a, i in enumerate(idx)}
        self.beliefs.return_scores(scores, modes, opts, returning)

        ranked = np.argsort(-np.where(np.isfinite(scores), scores, -1e300), axis=1, kind="stable")
        pick = b.claim(ranked, opts, seen.positions, seen.distances, flying)
        rows = np.arange(n)
        next_cells = np.where(flying[:, None], opts.cells[rows, pick], self.beliefs.cells)
        next_headings = np.where(flying, opts.headings[rows, pick], self.beliefs.headings)
        modes[~flying] = MODES.index("hold")
        self._remember_plans(best_paths, next_cells, flying)

        # HAPF-ACO's engagement rule, over the same UAVs (a returning one included)
        engage = b.engage_requests((self.beliefs.track[:, 0] >= 0) & flying)
        return StepDecision(next_cells, next_headings, engage, self.beliefs.done.copy(), modes)

    def _remember_plans(
        self,
        best: dict[int, tuple[np.ndarray, np.ndarray]],
        next_cells: np.ndarray,
        flying: np.ndarray,
    ) -> None:
        """Keep each UAV's best path if it flies its first move (announced to neighbours and
        used as the next step's warm start); otherwise forget it."""
        self.plan_valid[:] = False
        for i, (path, turns) in best.items():
            if flying[i] and np.array_equal(path[0], next_cells[i]):
                self.plans[i] = path
                self.plan_turns[i] = turns
                self.plan_valid[i] = True

    # ------------------------------------------------------------------ the particle swarms

    def _optimise(
        self, idx: np.ndarray, engaging: np.ndarray, opts: MoveOptions, hears: np.ndarray
    ):
        """PSO for the UAVs ``idx`` at once. Returns (scores per candidate (m, C), best path
        cells (m, H, 2), best path turns (m, H))."""
        s, k = self.settings, self.max_turn
        m, P, H = len(idx), s.particles, s.horizon_steps
        rng = self.rng
        value = self._window_values(idx, hears)
        terminal = self._terminal_values(idx)
        tables = self._constraint_tables(idx)
        bound = k + 0.49

        x = rng.uniform(-bound, bound, size=(m, P, H))
        x[:, 1] = 0.0
        warm = self.plan_valid[idx] & (self.plans[idx, 0] == self.beliefs.cells[idx]).all(axis=1)
        shifted = np.concatenate([self.plan_turns[idx, 1:], np.zeros((m, 1))], axis=1)
        x[warm, 0] = shifted[warm]
        v = rng.uniform(-s.velocity_max, s.velocity_max, size=(m, P, H))

        fit, first = self._fitness(idx, engaging, x, value, terminal, tables)
        cand_best = np.full((m, opts.cells.shape[1]), -np.inf)
        self._note_first_moves(cand_best, fit, first)
        p_best, p_fit = x.copy(), fit.copy()
        for _ in range(s.iterations - 1):
            g = p_best[np.arange(m), np.argmax(p_fit, axis=1)]  # (m, H)
            r1, r2 = rng.random((2, m, P, H))
            v = (
                s.inertia * v
                + s.cognitive * r1 * (p_best - x)
                + s.social * r2 * (g[:, None, :] - x)
            )
            v = _clamp(v, -s.velocity_max, s.velocity_max)
            x = _clamp(x + v, -bound, bound)
            fit, first = self._fitness(idx, engaging, x, value, terminal, tables)
            self._note_first_moves(cand_best, fit, first)
            better = fit > p_fit
            p_best[better] = x[better]
            p_fit = np.where(better, fit, p_fit)
        g = p_best[np.arange(m), np.argmax(p_fit, axis=1)]
        turns = np.rint(g)  # |x| <= k + 0.49 rounds into [-k, k]
        cells, _ = self._decode(idx, turns[:, None, :])
        feasible = opts.feasible[idx]
        scores = np.where(feasible, np.where(np.isfinite(cand_best), cand_best, -1e9), -np.inf)
        return scores, cells[:, 0], turns

    def _note_first_moves(self, cand_best: np.ndarray, fit: np.ndarray, first: np.ndarray) -> None:
        for c in range(cand_best.shape[1]):
            cand_best[:, c] = np.maximum(
                cand_best[:, c], np.where(first == c, fit, -np.inf).max(axis=1)
            )

    def _decode(self, idx: np.ndarray, turns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Turn commands (m, P, H) -> path cells (m, P, H, 2) and headings (m, P, H) (C_m by
        construction)."""
        heads = np.mod(
            self.beliefs.headings[idx][:, None, None] + np.cumsum(turns.astype(np.int64), axis=2), 8
        )
        cells = self.beliefs.cells[idx][:, None, None, :] + np.cumsum(HEADING_STEPS[heads], axis=2)
        return cells, heads

    def _constraint_tables(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What C_t and C_r say about every cell a path can reach, once per step: ``allowed``
        (m, 8, E), the move from window cell e along heading h is safe and viable
        (``SafetyModel.move_allowed``, with the threats each UAV knows); ``home`` (m, E), the
        shortest safe path home from window cell e (inf outside the area). The window is the
        (2H + 1)^2 cells within H moves of the UAV."""
        grid = self.grid
        m, e = len(idx), len(self.end_offsets)
        cells = self.beliefs.cells[idx][:, None, :] + self.end_offsets[None]  # (m, E, 2)
        heads = np.broadcast_to(np.arange(8)[:, None], (8, e))
        allowed = np.zeros((m, 8, e), dtype=bool)
        home = np.full((m, e), np.inf)
        inside = grid.inside(cells)
        flat = grid.clipped_flat(cells)
        for known, rows in threat_groups(self.beliefs.known_threats[idx]):
            model = self.beliefs.safety_model(known)
            at = np.broadcast_to(cells[rows][:, None], (len(rows), 8, e, 2))
            allowed[rows] = model.move_allowed(at, np.broadcast_to(heads, (len(rows), 8, e)))
            if np.isfinite(self.cfg.max_range_km):
                for a in rows:
                    field = model.distance_home_km(int(self.beliefs.home_flat[idx[a]])).ravel()
                    home[a] = np.where(inside[a], field[flat[a]], np.inf)
        return allowed, home

    def _feasible_prefix(self, idx: np.ndarray, cells: np.ndarray, heads: np.ndarray,
                         tables: tuple[np.ndarray, np.ndarray]) -> np.ndarray:  # fmt: skip
        """(m, P, H) bool: move j and all before it satisfy C_t (viable) and C_r."""
        cfg, h = self.cfg, self.settings.horizon_steps
        allowed_tab, home_tab = tables
        m = len(idx)
        offset = cells - self.beliefs.cells[idx][:, None, None, :]
        flat = (offset[..., 0] + h) * (2 * h + 1) + (offset[..., 1] + h)  # window index of cells
        prev = np.concatenate(
            [np.full(flat[:, :, :1].shape, len(self.end_offsets) // 2), flat[:, :, :-1]], axis=2
        )
        rows = np.arange(m)[:, None, None]
        allowed = allowed_tab[rows, heads, prev]
        if np.isfinite(cfg.max_range_km):
            flown = (
                self.beliefs.distance_km[idx][:, None, None]
                + np.cumsum(HEADING_LENGTHS[heads], axis=2) * cfg.cell_km
            )
            allowed &= flown + home_tab[rows, flat] + cfg.return_reserve_km <= cfg.max_range_km
        return np.cumprod(allowed, axis=2).astype(bool)

    def _fitness(self, idx, engaging, x, value, terminal_table, tables):
        """Eq 7's objective for every particle path: (fitness (m, P), first-move index (m, P))."""
        s, k, cfg = self.settings, self.max_turn, self.cfg
        m, P, H = x.shape
        turns = np.rint(x).astype(np.int64)  # |x| <= k + 0.49: C_m holds
        cells, heads = self._decode(idx, turns)
        ok = self._feasible_prefix(idx, cells, heads, tables)
        n_ok = ok.sum(axis=2)

        # search (omega = 0): unique cells of the footprints along the feasible prefix
        w, h = self.window, s.horizon_steps
        side = 2 * w + 1
        offset = cells - self.beliefs.cells[idx][:, None, None, :]  # within +-H of the UAV
        flat = (offset[..., 0] + w) * side + (offset[..., 1] + w)
        flat = flat[..., None] + self.footprint_flat  # (m, P, H, K) window indices
        flat = np.where(ok[..., None], flat, side * side)
        flat = np.sort(flat.reshape(m, P, -1), axis=2)
        gathered = value[np.arange(m)[:, None, None], flat]
        gathered[..., 1:] = np.where(flat[..., 1:] == flat[..., :-1], 0.0, gathered[..., 1:])
        last = np.maximum(n_ok - 1, 0)
        end = np.take_along_axis(offset, last[:, :, None, None], axis=2)[:, :, 0]
        end = np.where((n_ok > 0)[..., None], end, 0)
        end_flat = (end[..., 0] + h) * (2 * h + 1) + (end[..., 1] + h)
        terminal = np.take_along_axis(terminal_table, end_flat, axis=1)
        search = gathered.sum(axis=2) + s.terminal_weight * terminal

        # attack (omega = 1): closest approach to the confirmed target, earlier is better
        fit = search
        if engaging.any():
            track = self.beliefs.track[idx]
            gap = np.hypot(*((cells - track[:, None, None, :]) * cfg.cell_km).transpose(3, 0, 1, 2))
            gap = np.where(ok, gap + 0.1 * np.arange(H), np.inf)
            here = np.hypot(*((self.beliefs.cells[idx] - track) * cfg.cell_km).T)
            attack = -np.minimum(gap.min(axis=2), here[:, None] + 0.1 * H)
            fit = np.where(engaging[:, None], attack, search)
        fit = fit - s.infeasible_penalty * (H - n_ok)
        return fit, turns[:, :, 0] + k

    def _window_values(self, idx: np.ndarray, hears: np.ndarray) -> np.ndarray:
        """Value of each cell of the window around each UAV (m, S + 1; the last entry, 0, stands
        for cells outside the area or off the feasible path)."""
        grid, s = self.grid, self.settings
        m = len(idx)
        w = self.window
        side = 2 * w + 1
        cells = self.beliefs.cells[idx][:, None, :] + self.window_offsets[None]
        inside = grid.inside(cells)
        p = self.beliefs.tpm.existence_at(idx[:, None], cells)
        share = p / np.maximum(p.max(axis=1, keepdims=True), 1e-12)
        covered = self.beliefs.coverage.reshape(self.n, -1)[idx[:, None], grid.clipped_flat(cells)]
        unsearched = ~covered & inside
        # cooperation: cells inside the footprints of the paths neighbours announced last step
        pairs_a, pairs_j = np.nonzero(hears[idx] & self.plan_valid[None, :])
        if pairs_a.size and s.horizon_steps > 1:
            ahead = self.plans[pairs_j, 1:]  # (Q, H-1, 2): the part not flown yet
            fp = ahead[:, :, None, :] + self.footprint[None, None]
            local = fp - (self.beliefs.cells[idx[pairs_a]] - w)[:, None, None, :]
            keep = ((local >= 0) & (local < side)).all(axis=-1)
            rows = np.broadcast_to(pairs_a[:, None, None], keep.shape)[keep]
            flat = local[keep][:, 0] * side + local[keep][:, 1]
            claimed = np.zeros((m, side * side), dtype=bool)
            claimed[rows, flat] = True
            unsearched &= ~claimed
        value = unsearched + s.tpm_weight * share * inside
        return np.concatenate([value, np.zeros((m, 1))], axis=1)

    def _terminal_values(self, idx: np.ndarray) -> np.ndarray:
        """Beyond-horizon value at every cell a path can end in, (m, (2H + 1)^2): the block
        values (refreshed every ``block_refresh_steps``) weighted by exp(-distance /
        ``terminal_length_km``)."""
        s, grid = self.settings, self.grid
        stale = idx[self.beliefs.k - self.block_step[idx] >= s.block_refresh_steps]
        if stale.size:
            b = s.block_cells
            bx, by = self.block_shape
            pad = ((0, bx * b - grid.nx), (0, by * b - grid.ny))
            beliefs = self.beliefs
            for i in stale:
                unsearched = np.pad(~beliefs.coverage[i], pad)
                unsearched = unsearched.reshape(bx, b, by, b).mean(axis=(1, 3))
                existence = np.pad(beliefs.tpm.existence_map(int(i)), pad)
                mass = existence.reshape(bx, b, by, b).sum(axis=(1, 3))
                self.block_value[i] = (unsearched + mass).ravel()
            self.block_step[stale] = self.beliefs.k
        ends = self.beliefs.cells[idx][:, None, :] + self.end_offsets[None]  # (m, E, 2)
        weights = self.block_weights[grid.clipped_flat(ends)]  # (m, E, B)
        return np.einsum("meb,mb->me", weights, self.block_value[idx])
