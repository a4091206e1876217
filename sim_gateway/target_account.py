"""The per-target account of a mission: what happened to every target, from ground truth.

Why did a mission miss a target? The account answers per target: its kind and value, the
decision steps it spent inside some UAV's sensor footprint (radius R = 3 km, the sensor's own
rule, ``World.footprint_hits``), its first sighting (first step in a footprint) and the looks
that reported it (b = 1 at its cell, eq 17), the highest probability the swarm's beliefs gave a
target within the engage radius of where it really was, when a UAV pursued it and when its
target counted as confirmed there, and whether it was engaged (step, UAV), missed (in a
footprint at some step, never engaged) or never seen. Totals: targets seen (in a footprint for
at least ``SEEN_MIN_STEPS`` steps), confirmed, engaged, and the conversion engaged / seen.

Two halves, joined here:

- **truth** (this module's ``TargetAccount``): kept next to the world by whoever holds it (the
  offline runner, the MAVLink simulator, a payload simulator for external autopilots): call
  ``observe`` at every decision step with the UAV positions of the looks, and
  ``record_engagement`` with each engagement's outcome; ``truth()`` is a JSON-ready dict;
- **planner facts** (``planner.pursuit_log.PursuitLog``): what the planner believed and
  pursued, without ground truth.

``account_of(truth, facts)`` joins them by decision step and position: a belief entry counts for
a target when its cell centre lies within the engage radius of the target's true position at
that step; a pursuit counts for the nearest live target within the engage radius plus
``PURSUIT_JOIN_CELLS`` cells of its cell.
Truth never reaches the planner: the account reads the world and the planner's log, and only
ever writes into the result.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from planner.engagement import EngagementOutcome
from planner.sensor_model import SensorReport
from sim_gateway.world import KIND_CODES, World

#: A target counts as seen when it was inside some footprint at this many decision steps.
SEEN_MIN_STEPS = 3
#: A pursued cell belongs to the nearest live target within this many cells (plus the engage
#: radius): the planner's track is a belief peak, which trails a moving target by a cell or two.
PURSUIT_JOIN_CELLS = 1.5
KIND_NAMES = {code: name for name, code in KIND_CODES.items()}
#: The kinds in the order of the paper's Table 1, and the funnel's stages.
KINDS = ("known_position", "known_speed", "known_velocity", "unknown_position")
STAGES = ("targets", "in_footprint", "seen", "pursued", "confirmed", "engaged")
OUTCOMES = ("engaged", "missed", "never seen")


class TargetAccount:
    """Ground-truth bookkeeping of every target of ``world`` over one mission."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.engaged_step = np.full(len(world.target_ids), -1, dtype=np.int64)
        self.engaged_uav = np.full(len(world.target_ids), -1, dtype=np.int64)
        self.steps: list[int] = []
        self.times_ms: list[int | None] = []
        self.positions: list[np.ndarray] = []  # (T, 2) km at each observed step
        self.inside: list[np.ndarray] = []  # target indices inside some footprint, per step
        self.detected: list[np.ndarray] = []  # ... and reported by a look (b = 1 at its cell)

    def observe(
        self,
        step: int,
        uav_xy_km: np.ndarray,
        airborne: np.ndarray | None = None,
        reports: Sequence[SensorReport | None] | None = None,
        time_ms: int | None = None,
    ) -> None:
        """Decision step ``step``: the UAVs looked from ``uav_xy_km`` (N, 2); only ``airborne``
        ones count. ``reports``, if given, are the looks the sensor returned, one per row of
        ``uav_xy_km`` (None for a UAV that did not look): a look with b = 1 at a target's cell
        counts as a detection of it. ``time_ms``: the looks' time stamp (``time_boot_ms`` of a
        simulator), by which ``align_steps`` finds a ground station's step. Call it with the
        world as it was at the looks."""
        world = self.world
        xy = np.asarray(uav_xy_km, dtype=float).reshape(-1, 2)
        flying = np.ones(len(xy), bool) if airborne is None else np.asarray(airborne, bool)
        self.steps.append(int(step))
        self.times_ms.append(None if time_ms is None else int(time_ms))
        self.positions.append(world.positions.copy())
        live = np.flatnonzero(world.alive)
        inside = np.zeros(len(world.target_ids), dtype=bool)
        if live.size and flying.any():
            _, target, _ = world.footprint_hits(world.grid.cell_of(xy[flying]), live)
            inside[live[target]] = True
        detected = np.zeros_like(inside)
        if reports is not None and inside.any():
            hit = np.zeros(world.grid.shape, dtype=bool)
            for i, report in enumerate(reports):
                if report is not None and flying[i]:
                    cells = report.cells[np.asarray(report.detected, dtype=bool)]
                    hit[cells[:, 0], cells[:, 1]] = True
            cells = world.grid.cell_of(world.positions)
            detected = inside & hit[cells[:, 0], cells[:, 1]]
        self.inside.append(np.flatnonzero(inside))
        self.detected.append(np.flatnonzero(detected))

    def record_engagement(self, step: int, uav: int, outcome: EngagementOutcome) -> None:
        """An engagement of UAV ``uav`` (0-based) at ``step`` came back with ``outcome``."""
        if not outcome.success:
            return
        index = np.flatnonzero(self.world.target_ids == outcome.target_id)
        if index.size and self.engaged_step[index[0]] < 0:
            self.engaged_step[index[0]] = step
            self.engaged_uav[index[0]] = uav

    def truth(self) -> dict:
        """The truth half as a JSON-ready dict (``account_of`` joins it with planner facts):
        per target its kind, value and engagement; per observed step the targets' positions and
        which targets were inside a footprint and detected."""
        world, cfg = self.world, self.world.config
        return {
            "detection_radius_km": cfg.detection_radius_km,
            "engage_radius_km": cfg.engage_radius_km,
            "cell_km": cfg.cell_km,
            "targets": [
                {
                    "id": int(world.target_ids[t]),
                    "kind": KIND_NAMES[int(world.kinds[t])],
                    "value": float(world.values[t]),
                    "engaged_step": _step(self.engaged_step[t]),
                    "engaged_uav": _step(self.engaged_uav[t]),
                }
                for t in range(len(world.target_ids))
            ],
            "steps": list(self.steps),
            "times_ms": list(self.times_ms),
            "positions_km": [np.round(p, 3).tolist() for p in self.positions],
            "in_footprint": [a.tolist() for a in self.inside],
            "detected": [a.tolist() for a in self.detected],
        }


def _step(value: int) -> int | None:
    return None if value < 0 else int(value)


def align_steps(truth: dict, step_times_ms: dict[int, int], tolerance_ms: float) -> dict:
    """``truth`` renumbered into a ground station's decision steps: a simulator counts its
    decision steps from its own start, a ground station from the take-off, so the two are
    joined by the looks' time stamps. ``step_times_ms`` maps each ground-station step to the
    time stamp of the looks it used; a truth step is kept when its ``times_ms`` lies within
    ``tolerance_ms`` of one (the nearest). An engagement keeps the step of the ground-station
    step that asked for it (the one matched to the truth step it happened in)."""
    times = np.array([np.nan if t is None else t for t in truth["times_ms"]], dtype=float)
    renumber: dict[int, int] = {}
    for step, stamp in sorted(step_times_ms.items()):
        if not len(times):
            break
        gap = np.abs(times - stamp)
        if np.isnan(gap).all():
            continue
        nearest = int(np.nanargmin(gap))
        if gap[nearest] <= tolerance_ms:
            renumber.setdefault(int(truth["steps"][nearest]), int(step))
    # an engagement at a truth step no look was matched to: the steps' usual offset
    offset = int(np.median([d - s for s, d in renumber.items()])) if renumber else 0
    kept = [i for i, s in enumerate(truth["steps"]) if s in renumber]
    aligned = dict(truth)
    for key in ("times_ms", "positions_km", "in_footprint", "detected"):
        aligned[key] = [truth[key][i] for i in kept]
    aligned["steps"] = [renumber[truth["steps"][i]] for i in kept]
    aligned["targets"] = [
        {**t, "engaged_step": renumber.get(t["engaged_step"], t["engaged_step"] + offset)
         if t["engaged_step"] is not None else None}
        for t in truth["targets"]
    ]  # fmt: skip
    return aligned


def account_of_ground_station(truth: dict, result: dict, step_s: float) -> dict:
    """The per-target account of a ground station's ``result`` (the daemon's: its
    ``planner_facts`` and ``look_times_ms``) against a simulator's ``truth``: the truth
    renumbered into the result's steps by the looks' time stamps (``align_steps``, within half a
    decision period of ``step_s``), joined with the planner facts, cut at the mission's last
    step. ``swarmplan demo`` and ``swarmplan account`` both join this way."""
    look_times = {int(step): int(ms) for step, ms in result.get("look_times_ms") or []}
    aligned = align_steps(truth, look_times, tolerance_ms=500.0 * step_s)
    return account_of(aligned, result.get("planner_facts"), last_step=result["steps"])


def _join_beliefs(beliefs: np.ndarray, at: np.ndarray, live: np.ndarray, truth_xy: np.ndarray,
                  cell_km: float, radius_km: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Per target, the highest belief entry within ``radius_km`` of its true position at the
    entry's step, and that step (-1 where none)."""
    t = truth_xy.shape[1]
    peak, peak_step = np.zeros(t), np.full(t, -1, dtype=np.int64)
    if not len(beliefs):
        return peak, peak_step
    centres = (beliefs[:, 1:3] + 0.5) * cell_km
    d = np.hypot(*(truth_xy[at] - centres[:, None, :]).transpose(2, 0, 1))  # (M, T)
    near = (d <= radius_km + 1e-9) & live[at]
    p = np.where(near, beliefs[:, 3:4], -1.0)
    best = p.argmax(axis=0)
    found = p[best, np.arange(t)] >= 0
    peak[found] = p[best[found], np.arange(t)[found]]
    peak_step[found] = beliefs[best[found], 0].astype(np.int64)
    return peak, peak_step


def _join_tracks(
    tracks: np.ndarray, at: np.ndarray, live: np.ndarray, truth_xy: np.ndarray, cell_km: float,
    radius_km: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Per target: first step pursued, by which UAV, first step confirmed (-1 where never)."""
    t = truth_xy.shape[1]
    pursued, by, confirmed = (np.full(t, -1, dtype=np.int64) for _ in range(3))
    if not len(tracks):
        return pursued, by, confirmed
    centres = (tracks[:, 2:4] + 0.5) * cell_km
    d = np.hypot(*(truth_xy[at] - centres[:, None, :]).transpose(2, 0, 1))  # (M, T)
    d = np.where(live[at], d, np.inf)
    nearest = d.argmin(axis=1)
    close = d[np.arange(len(tracks)), nearest] <= radius_km + 1e-9
    for m in np.flatnonzero(close):  # tracks are in step order
        target, step = nearest[m], int(tracks[m, 0])
        if pursued[target] < 0:
            pursued[target], by[target] = step, int(tracks[m, 1])
        if tracks[m, 4] and confirmed[target] < 0:
            confirmed[target] = step
    return pursued, by, confirmed


def account_of(truth: dict, facts: dict | None = None, last_step: int | None = None) -> dict:
    """The per-target account: the truth half (``TargetAccount.truth``) joined with the
    planner's facts (``PursuitLog.facts``; None leaves belief, pursuit and confirmation out),
    over the steps up to ``last_step`` (default all; a simulator runs on after the mission).
    Returns ``{"targets": rows, "totals": counts, "by_kind": {kind: counts}}``."""
    rows = []
    for r in truth["targets"]:
        row = {k: r[k] for k in ("id", "kind", "value")}
        late = last_step is not None and (r["engaged_step"] or 0) > last_step
        row["engaged_step"] = None if late else r["engaged_step"]
        row["engaged_uav"] = None if late else r["engaged_uav"]
        rows.append(row)
    t = len(rows)
    kept = [i for i, s in enumerate(truth["steps"]) if last_step is None or s <= last_step]
    steps = [truth["steps"][i] for i in kept]
    index = {s: i for i, s in enumerate(steps)}
    positions = np.asarray([truth["positions_km"][i] for i in kept], dtype=float).reshape(
        len(steps), t, 2
    )
    inside = np.zeros((len(steps), t), dtype=bool)
    detected = np.zeros((len(steps), t), dtype=bool)
    for row_index, i in enumerate(kept):
        inside[row_index, truth["in_footprint"][i]] = True
        detected[row_index, truth["detected"][i]] = True
    step_arr = np.asarray(steps, dtype=np.int64)
    for k, row in enumerate(rows):
        row["steps_in_footprint"] = int(inside[:, k].sum())
        row["first_sighting"] = int(step_arr[inside[:, k]][0]) if inside[:, k].any() else None
        row["detections"] = int(detected[:, k].sum())
        row["first_detection"] = int(step_arr[detected[:, k]][0]) if detected[:, k].any() else None
    engaged = np.array([-1 if r["engaged_step"] is None else r["engaged_step"] for r in rows])
    live = (engaged[None, :] < 0) | (step_arr[:, None] <= engaged[None, :])  # (S, T)
    joined = facts is not None
    if joined:
        cell_km = float(facts.get("cell_km", truth["cell_km"]))
        beliefs = _rows_at(facts.get("beliefs", []), 4, index)
        tracks = _rows_at(facts.get("tracks", []), 5, index)
        peak, peak_step = _join_beliefs(
            beliefs, _at(beliefs, index), live, positions, cell_km, truth["engage_radius_km"]
        )
        pursued, by, confirmed = _join_tracks(
            tracks, _at(tracks, index), live, positions, cell_km,
            truth["engage_radius_km"] + PURSUIT_JOIN_CELLS * cell_km,
        )  # fmt: skip
    for k, row in enumerate(rows):
        row["seen"] = row["steps_in_footprint"] >= SEEN_MIN_STEPS
        if joined:
            row["belief_peak"] = round(float(peak[k]), 4)
            row["belief_peak_step"] = _step(peak_step[k])
            row["pursued_step"] = _step(pursued[k])
            row["pursued_by"] = _step(by[k])
            row["confirmed_step"] = _step(confirmed[k])
        row["outcome"] = (
            "engaged" if row["engaged_step"] is not None
            else "missed" if row["steps_in_footprint"] > 0
            else "never seen"
        )  # fmt: skip
    by_kind = {kind: _counts([r for r in rows if r["kind"] == kind], joined) for kind in KINDS}
    return {
        "seen_min_steps": SEEN_MIN_STEPS,
        "targets": rows,
        "totals": _counts(rows, joined),
        "by_kind": {k: v for k, v in by_kind.items() if v["targets"]},
    }


def _rows_at(entries: list, width: int, index: dict[int, int]) -> np.ndarray:
    """Fact entries (lists of ``width`` numbers) at the steps truth observed, as an array."""
    kept = [e for e in entries if int(e[0]) in index]
    return np.asarray(kept, dtype=float).reshape(len(kept), width)


def _at(entries: np.ndarray, index: dict[int, int]) -> np.ndarray:
    return np.array([index[int(s)] for s in entries[:, 0]], dtype=np.int64)


def _counts(rows: Sequence[dict], joined: bool) -> dict:
    """The funnel of ``rows``: targets, in a footprint, seen, (pursued, confirmed,) engaged,
    missed, never seen, and the conversion engaged / seen (None when nothing was seen)."""
    seen = sum(r["seen"] for r in rows)
    engaged = sum(r["outcome"] == "engaged" for r in rows)
    counts = {
        "targets": len(rows),
        "in_footprint": sum(r["steps_in_footprint"] > 0 for r in rows),
        "seen": seen,
        "pursued": sum(r["pursued_step"] is not None for r in rows) if joined else None,
        "confirmed": sum(r["confirmed_step"] is not None for r in rows) if joined else None,
        "engaged": engaged,
        "missed": sum(r["outcome"] == "missed" for r in rows),
        "never_seen": sum(r["outcome"] == "never seen" for r in rows),
        "engaged_value": float(sum(r["value"] for r in rows if r["outcome"] == "engaged")),
    }
    counts["conversion"] = round(engaged / seen, 4) if seen else None
    return counts


def format_account(account: dict) -> str:
    """The account's totals in one line, for run summaries."""
    c = account["totals"]
    conversion = "n/a" if c["conversion"] is None else f"{c['conversion']:.2f}"
    confirmed = "" if c["confirmed"] is None else f", confirmed {c['confirmed']}"
    return (
        f"targets         {c['targets']}: seen {c['seen']} (>= {account['seen_min_steps']} steps"
        f" in a footprint){confirmed}, engaged {c['engaged']}, conversion {conversion}"
    )
