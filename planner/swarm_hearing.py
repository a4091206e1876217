"""What each UAV of a swarm hears at a decision step (section 3.3.1: only the neighbours inside
its cooperative radius reach it), the second and third parts of ``SwarmBeliefs``'s step
(``planner.swarm_beliefs``): the topology (eqs 1-3), the swarm information of eqs 30-31, the
threats and serviced targets heard, the looks (probe update, eqs 16-18), the engagement choice
(section 3.2.1) and one UAV per target (``leave_to_nearer``).

``SwarmHearing`` is a part of ``SwarmBeliefs`` (a base class of it): its methods read and write
the beliefs' arrays, documented there.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from planner.sensor_model import SensorReport
from planner.topology import adapt_radius


@dataclass(frozen=True)
class Hearing:
    """What ``SwarmBeliefs.observe`` found at this step, for the decision. Rows are the UAVs
    whose beliefs are kept (``SwarmBeliefs.owners``), columns the swarm's members."""

    flying: np.ndarray  # (n,) bool: reachable and not done
    hears: np.ndarray  # (n, N) bool: owner i hears member j (eqs 1-3)
    positions: np.ndarray  # (N, 2) km, the members' cell centres
    distances: np.ndarray  # (n, N) km from each owner to each member
    members_flying: np.ndarray  # (N,) bool
    received: np.ndarray  # (N,) bool: the member's state arrived this step


@dataclass(frozen=True)
class HeardSwarm:
    """What the owners know of every member of the swarm at this step, after the first part of
    the step (``SwarmBeliefs.begin_step``): their own rows, and the others' from what they sent
    (``planner.swarm_messages``; a member not heard from is not ``received``)."""

    cells: np.ndarray  # (N, 2) int
    headings: np.ndarray  # (N,) int
    flying: np.ndarray  # (N,) bool: flying (and heard from)
    received: np.ndarray  # (N,) bool: its state arrived this step (the owners' own: True)
    reports: Sequence[SensorReport | None]  # N looks
    known_threats: np.ndarray  # (N, T) bool, each member's after its own detection
    known_engaged: np.ndarray  # (N, G) bool, each member's after its own engagement outcome
    engaged_cells: np.ndarray  # (G, 2) int: where each serviced target was engaged, or -1


class SwarmHearing:
    """The hearing part of ``planner.swarm_beliefs.SwarmBeliefs`` (see the module's docstring)."""

    def hear(self, view: HeardSwarm) -> Hearing:
        """The step's second part: topology (eqs 1-3) and what each owner hears of the swarm
        (``view``): the swarm information of eqs 30-31, threats and serviced targets heard,
        looks (eqs 16-18) and the engagement choice before ``leave_to_nearer``."""
        cfg, own, flying = self.cfg, self.owners, self.flying
        self._options = None  # the threats heard change C_t
        positions = self.grid.centre_km(view.cells)
        diff = positions[own][:, None, :] - positions[None, :, :]
        distances = np.hypot(diff[..., 0], diff[..., 1])
        hears = distances <= self.radius_km[:, None]
        hears[np.arange(self.n), own] = False
        hears &= flying[:, None] & view.flying[None, :] & view.received[None, :]
        self.radius_km = np.where(
            flying, adapt_radius(self.radius_km, hears.sum(axis=1), cfg), self.radius_km
        )
        listen = hears.copy()
        listen[np.arange(self.n), own] = flying
        self.info_cells = np.where(listen[:, :, None], view.cells[None, :, :], self.info_cells)
        self.info_headings = np.where(listen, view.headings[None, :] % 8, self.info_headings)
        self.info_step = np.where(listen, self.k, self.info_step)
        if len(self.threat_r):  # threats found by the neighbours
            heard = hears.astype(np.int64) @ view.known_threats.astype(np.int64)
            self.known_threats |= heard > 0
        self._hear_engaged(view, hears)
        have = np.array([r is not None and len(r.cells) > 0 for r in view.reports], dtype=bool)
        self._apply_looks(view.reports, have, listen, positions)
        self._update_tracks(view.reports, have, listen)
        return Hearing(flying, hears, positions, distances, view.flying, view.received)

    def _hear_engaged(self, view: HeardSwarm, hears: np.ndarray) -> None:
        """What the owners hear of serviced targets; each is taken out of the TPM of an owner
        that newly knows of it."""
        heard = hears.astype(np.int64) @ view.known_engaged.astype(np.int64)
        self.known_engaged |= heard > 0
        unknown = self.engaged_cells[:, 0] < 0
        self.engaged_cells[unknown] = view.engaged_cells[unknown]
        for i, t in zip(*np.nonzero(self.known_engaged & ~self.engaged_applied), strict=True):
            self.tpm.remove_target(int(i), int(self.target_ids[t]), self.engaged_cells[t])
        self.engaged_applied = self.known_engaged.copy()

    def _apply_looks(
        self,
        reports: Sequence[SensorReport | None],
        have: np.ndarray,
        listen: np.ndarray,
        positions: np.ndarray,
    ) -> None:
        """``have[j]``: UAV j reported a look with at least one cell."""
        pairs = listen & have[None, :]  # receiver i gets look j
        receivers, sources = np.nonzero(pairs)
        if receivers.size == 0:
            self.tpm.renormalise()
            return
        origins = self.grid.cell_of(positions)
        look_cells = [reports[j].cells for j in sources]
        self.tpm.apply_looks(
            receivers, look_cells, [reports[j].detected for j in sources], origins[sources]
        )
        # coverage each UAV knows of, and the N_t counter of steps without a gain
        seen_by = np.repeat(receivers, [len(c) for c in look_cells])
        seen = np.concatenate(look_cells)
        # only the cells new to their receiver change the counts: set and count those
        covered = self.coverage.reshape(-1)
        keys = seen_by * self.grid.size + self.grid.flat(seen)
        fresh = distinct(keys[~covered[keys]])
        covered[fresh] = True
        new_cells = np.bincount(fresh // self.grid.size, minlength=self.n)
        self.coverage_count = self.coverage_count + new_cells
        gained = new_cells > 0
        self.stall_steps = np.where(gained, 0, self.stall_steps + 1)
        self.escape_goal[gained] = -1
        if self.cfg.tpm_decay_tau < 1.0:
            observed = np.zeros(self.coverage.shape, dtype=bool)
            observed[seen_by, seen[:, 0], seen[:, 1]] = True
            self.tpm.decay_unobserved(observed)
        self.tpm.renormalise()

    def _update_tracks(
        self,
        reports: Sequence[SensorReport | None],
        have: np.ndarray,
        listen: np.ndarray,
    ) -> None:
        """Section 3.2.1: choose the cell each UAV goes for. Candidates are the cells it just heard
        a detection in and the cells around its current track (the belief peak moves with the
        target).
        A cell whose existence probability reaches ``pursue_threshold`` is worth a closer look
        (the attraction of eq 24 toward a rising p); one that reaches ``confirm_threshold`` is a
        confirmed target, and confirmed targets come first, the higher value first. Batched over
        UAVs: one TPM read for all (UAV, cell) pairs."""
        cfg = self.cfg
        rows: list[np.ndarray] = []
        cells: list[np.ndarray] = []
        tracking = np.flatnonzero((self.track[:, 0] >= 0) & ~self.done)
        if tracking.size:
            rows.append(np.repeat(tracking, len(self.track_window)))
            cells.append(
                (self.track[tracking][:, None, :] + self.track_window[None]).reshape(-1, 2)
            )
        receivers, sources = np.nonzero(listen & have[None, :] & ~self.done[:, None])
        if receivers.size:
            # only a detection (b = 1) raises a cell's probability: the cells worth checking
            by_source = {
                j: reports[j].cells[np.asarray(reports[j].detected, dtype=bool)]
                for j in np.unique(sources).tolist()
            }
            positive = [by_source[j] for j in sources.tolist()]
            rows.append(np.repeat(receivers, [len(c) for c in positive]))
            cells.append(np.concatenate(positive))
        previous = self.track.copy()
        self.track[:] = -1
        if not rows:
            return
        rows_all, cells_all = np.concatenate(rows), np.concatenate(cells)
        reach = np.hypot(*((cells_all - self.cells[rows_all]) * cfg.cell_km).T)
        keep = self.grid.inside(cells_all) & (reach <= cfg.pursue_range_km)
        rows_all, cells_all = rows_all[keep], cells_all[keep]
        # one look per distinct (UAV, cell): heard footprints overlap
        keys = distinct(rows_all * self.grid.size + self.grid.flat(cells_all))
        rows_all = keys // self.grid.size
        cells_all = np.column_stack(np.unravel_index(keys % self.grid.size, self.grid.shape))
        p = self.engage_probability(rows_all, cells_all)
        # a suspect already pursued is kept (hysteresis) while its peak stays above
        # ``pursue_keep_threshold``, for at most ``pursue_max_steps`` steps: one look that
        # misses a moving target does not end its pursuit; looks that find nothing rule it out
        on_track = (previous[rows_all, 0] >= 0) & (
            np.abs(cells_all - previous[rows_all]).max(axis=1) <= 2
        )
        kept = on_track & (self.track_age[rows_all] < cfg.pursue_max_steps)
        worth = (p >= cfg.pursue_threshold) | (kept & (p >= cfg.pursue_keep_threshold))
        if not worth.any():
            self.track_age[:] = 0
            return
        rows_all, cells_all, p = rows_all[worth], cells_all[worth], p[worth]
        on_track = on_track[worth]
        value = self.tpm.values_at(rows_all, cells_all)
        confirmed = p >= cfg.confirm_threshold
        # confirmed first (higher value first), then the likeliest value among the suspects;
        # among equal scores (the cells around one confirmed target, whose layer gives them one
        # value) the likeliest cell, not the first in index order
        score = np.where(confirmed, 1.0 + value, 0.0) + np.where(
            confirmed, 0.0, p * value / (1.0 + value)
        )
        order = np.lexsort((-p, -score, rows_all))
        sorted_rows = rows_all[order]
        first = np.concatenate(([True], sorted_rows[1:] != sorted_rows[:-1]))
        chosen = order[first]
        who = rows_all[chosen]
        self.track[who] = cells_all[chosen]
        self.track_confirmed[who] = confirmed[chosen]
        age = np.zeros(self.n, dtype=np.int64)
        age[who] = np.where(on_track[chosen], self.track_age[who] + 1, 0)
        self.track_age = age

    def leave_to_nearer(
        self, seen: Hearing, cells: np.ndarray, headings: np.ndarray, tracks: np.ndarray
    ) -> None:
        """The step's third part, one UAV per target, the best placed: an owner drops its track
        when a member it hears goes for the same or an adjacent cell (``tracks``, (N, 2), -1
        for none, as the members chose them in ``hear``) in fewer turn-limited moves
        (``steps_to_reach`` from its heading, ``cells`` and ``headings`` (N, ...): a UAV next to
        a target but flying away from it is worse placed than one a few cells off pointing at
        it; ties to the lower index), instead of the swarm converging."""
        own = self.owners
        tracking = tracks[:, 0] >= 0
        same = np.abs(self.track[:, None, :] - tracks[None, :, :]).max(axis=2) <= 1
        same &= (self.track[:, 0] >= 0)[:, None] & tracking[None, :] & seen.hears
        if not same.any():
            return
        r = self.pursuit_reach
        offset = tracks - cells
        inside = (np.abs(offset) <= r).all(axis=1)
        ox, oy = np.clip(offset + r, 0, 2 * r).T
        steps = self.pursuit_steps[headings % 8, ox, oy].astype(float)
        gap = np.where(inside, steps, 1e6 + np.hypot(*offset.T))
        mine = gap[own][:, None]
        nearer = (gap[None, :] < mine) | (
            (gap[None, :] == mine) & (np.arange(self.size)[None, :] < own[:, None])
        )
        self.track[(same & nearer).any(axis=1)] = -1


def distinct(values: np.ndarray) -> np.ndarray:
    """``np.unique`` of a 1-D array (sorted distinct values), without its overhead on the small
    arrays of one step."""
    ordered = np.sort(values)
    if ordered.size == 0:
        return ordered
    return ordered[np.concatenate(([True], ordered[1:] != ordered[:-1]))]
