"""Mission metrics and safety accounting (eqs 4-5), from positions as they really were.

The offline runner feeds it the world's positions; the MAVLink daemon feeds it telemetry. Both
get the same result dictionary (the ``result.json`` of a run):

- J_T: value of the targets engaged (``engaged_value``), and how many (``engaged_count``);
- J_E: the share of cells that were ever inside a sensor footprint (``coverage``), after each
  step (``coverage_curve[k]`` after k steps, k = 0 is the start) and the slope of its first 50
  steps (``coverage_slope_50``, share per step);
- separation: minimum pairwise distance of the airborne UAVs, per step and overall;
- distance flown per UAV, whether it came back to its start;
- UAV-steps the planner spent in each of its decision modes (``decision_modes``: search by the
  transition rules, the potential field's deterministic move, escape, pursuit and engagement,
  the return of C_r, hold), so a flown run's conduct can be set beside the offline one's;
- violations of C_t (inside a threat, or a leg crossing one), C_c (pair closer than d_min),
  C_m (turn over phi_max between consecutive legs) and C_r (distance over L_max).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from planner.constraints import segment_clearance
from planner.grid import Grid
from planner.planner_interface import MODES
from planner.scenario import Scenario, UavStart
from planner.topology import pairwise_distances


class MissionRecorder:
    def __init__(
        self,
        scenario: Scenario,
        starts: Sequence[UavStart],
        turn_tolerance_deg: float = 1e-6,
        home_reach_km: float = 0.0,
    ) -> None:
        """``home_reach_km``: how far a flown plane that is home may be from its home cell (a
        plane circling its home strays up to its loiter diameter from the point; 0 for the
        planner's own grid positions, see :meth:`returned`)."""
        cfg = scenario.config
        self.home_reach_km = home_reach_km
        self.scenario = scenario
        self.cfg = cfg
        self.grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
        self.n = len(starts)
        self.starts = np.array([[s.x_km, s.y_km] for s in starts], float)
        self.turn_tolerance_deg = turn_tolerance_deg
        self.covered = np.zeros(self.grid.shape, dtype=bool)
        self.footprint = self.grid.disc_offsets(cfg.detection_radius_km)
        self.threat_xy = np.array([[t.x_km, t.y_km] for t in scenario.threats], float).reshape(
            -1, 2
        )
        self.threat_r = np.array([t.radius_km for t in scenario.threats], float)
        self.tracks: list[list[list[float]]] = [[] for _ in range(self.n)]
        self.planned: list[list[list[float]]] = [[] for _ in range(self.n)]
        self.distance_km = np.zeros(self.n)
        self.coverage_curve: list[float] = []
        self.engaged_curve: list[int] = []
        self.min_separation_curve: list[float] = []
        self.mean_min_separation_curve: list[float] = []
        self.engagements: list[dict] = []
        self.engage_misses = 0  # engagements requested where no target was within the radius
        self.mode_steps = np.zeros(len(MODES), dtype=np.int64)  # UAV-steps in each decision mode
        #: ``home_by_end``: every UAV turned home at the first step (no time to go out and back)
        self.turned_home_at_start = False
        self.violations = {"threat": 0, "separation": 0, "turn": 0, "range": 0}
        self._last = np.full((self.n, 2), np.nan)
        self._last_leg = np.full((self.n, 2), np.nan)
        self._done = np.zeros(self.n, dtype=bool)
        self.steps = 0

    def record_step(self, positions_km: np.ndarray, airborne: np.ndarray | None = None,
                    planned_km: np.ndarray | None = None,
                    done: np.ndarray | None = None) -> None:  # fmt: skip
        """Positions (N, 2) of the UAVs at one decision step. ``airborne`` marks the UAVs that
        count (lost or landed ones do not); ``planned_km`` is where the planner sent them next."""
        cfg = self.cfg
        pos = np.asarray(positions_km, dtype=float).reshape(self.n, 2)
        airborne = (
            np.ones(self.n, dtype=bool) if airborne is None else np.asarray(airborne, dtype=bool)
        )
        if done is not None:
            self._done |= np.asarray(done, dtype=bool)
        for track, (x, y) in zip(self.tracks, pos.tolist(), strict=True):
            track.append([round(x, 4), round(y, 4)])
        if planned_km is not None:
            planned = np.asarray(planned_km, dtype=float).reshape(self.n, 2).tolist()
            for plan, (x, y) in zip(self.planned, planned, strict=True):
                plan.append([round(x, 4), round(y, 4)])
        # coverage J_E (eq 4)
        cells = self.grid.cell_of(pos[airborne])[:, None, :] + self.footprint[None]
        cells = cells[self.grid.inside(cells)]
        self.covered[cells[:, 0], cells[:, 1]] = True
        self.coverage_curve.append(np.count_nonzero(self.covered) / self.covered.size)
        self.engaged_curve.append(len(self.engagements))
        # legs: distance, turns, threat crossings
        has_last = ~np.isnan(self._last[:, 0]) & airborne
        legs = pos - self._last
        lengths = np.where(has_last, np.hypot(legs[:, 0], legs[:, 1]), 0.0)
        self.distance_km += lengths
        moving = has_last & (lengths > 1e-9)
        if len(self.threat_r):
            inside = segment_clearance(
                np.where(moving[:, None], self._last, pos), pos, self.threat_xy, self.threat_r
            )
            self.violations["threat"] += int(np.sum((inside < -1e-9) & airborne))
        prev_ok = moving & ~np.isnan(self._last_leg[:, 0])
        if prev_ok.any():
            a = np.arctan2(self._last_leg[prev_ok, 1], self._last_leg[prev_ok, 0])
            b = np.arctan2(legs[prev_ok, 1], legs[prev_ok, 0])
            turn = np.degrees(np.abs(np.mod(b - a + np.pi, 2 * np.pi) - np.pi))
            self.violations["turn"] += int(
                np.sum(turn > cfg.max_turn_deg + self.turn_tolerance_deg)
            )
        self._last_leg = np.where(moving[:, None], legs, self._last_leg)
        self._last = np.where(airborne[:, None], pos, self._last)
        if math.isfinite(cfg.max_range_km):
            over = self.distance_km > cfg.max_range_km + 1e-6
            self.violations["range"] += int(np.sum(over & moving))
        # separation C_c among airborne UAVs that have not landed back home
        flying = airborne & ~self._done
        if flying.sum() >= 2:
            p = pos[flying]
            d = pairwise_distances(p)
            np.fill_diagonal(d, np.inf)
            nearest = d.min(axis=1)
            self.min_separation_curve.append(float(nearest.min()))
            self.mean_min_separation_curve.append(float(nearest.mean()))
            # d is symmetric (and inf on the diagonal): each close pair is counted twice
            close = np.count_nonzero(d < cfg.min_separation_km - 1e-9)
            self.violations["separation"] += int(close) // 2
        else:
            self.min_separation_curve.append(math.inf)
            self.mean_min_separation_curve.append(math.inf)
        self.steps += 1

    def record_engagement(self, step: int, uav: int, target_id: int, value: float) -> None:
        self.engagements.append(
            {"step": int(step), "uav": int(uav), "target_id": int(target_id), "value": float(value)}
        )
        if self.engaged_curve:
            self.engaged_curve[-1] = len(self.engagements)

    def break_legs(self) -> None:
        """Start every UAV's chain of legs afresh: the next recorded position is not joined to
        the last one by a leg (no distance, no turn, no threat crossing judged between them),
        e.g. after an outage during which something other than the planner flew the vehicles."""
        self._last[:] = np.nan
        self._last_leg[:] = np.nan

    def __setstate__(self, state: dict) -> None:
        """Unpickled from a daemon checkpoint written before decision modes were counted: they
        are counted from the resumed step on."""
        state.setdefault("mode_steps", np.zeros(len(MODES), dtype=np.int64))
        state.setdefault("turned_home_at_start", False)
        self.__dict__.update(state)

    def record_modes(self, modes: np.ndarray) -> None:
        """The planner's decision mode of every UAV at one step (indices into ``MODES``). At the
        first step, with ``home_by_end``, every UAV in the return mode means the mission is too
        short to go out and come back with the steps kept in reserve (``home_reserve_steps``,
        and the daemon's more): px4-3uav flown as 12 steps stayed at home."""
        modes = np.asarray(modes, dtype=np.int64)
        if not self.mode_steps.any() and self.cfg.home_by_end and len(modes):
            self.turned_home_at_start = bool((modes == MODES.index("return")).all())
        self.mode_steps += np.bincount(modes, minlength=len(MODES))

    def record_engagement_miss(self) -> None:
        """An engagement was requested and nothing was within the engage radius."""
        self.engage_misses += 1

    def returned(self) -> np.ndarray:
        """UAVs at home at the last step, that did fly: the planner's last cell within one cell
        of the start's, and the position flown there within that cell's reach plus
        ``home_reach_km``. Offline both are the grid position (the cell rule alone); a flown
        plane told to circle its home cell is 1.6-2.9 km from the cell's centre at a decision
        instant (paper-10uav demo, 100 m/s), home all the same."""
        if not self.steps:
            return np.zeros(self.n, dtype=bool)
        last = np.array([t[-1] for t in self.tracks])
        ends = zip(self.planned, self.tracks, strict=True)
        plan = np.array([p[-1] if p else t[-1] for p, t in ends])
        start_cells = self.grid.cell_of(self.starts)
        planned_home = np.abs(self.grid.cell_of(plan) - start_cells).max(axis=1) <= 1
        reach = 1.5 * self.grid.cell_km + self.home_reach_km
        flown_home = np.abs(last - self.grid.centre_km(start_cells)).max(axis=1) <= reach + 1e-9
        return planned_home & flown_home & (self.distance_km > 2 * self.cfg.step_km)

    def result(
        self, seed: int, algorithm: str, wall_time_s: float, extra: dict | None = None
    ) -> dict:
        from scipy import stats  # here: scipy.stats takes most of a second to import

        curve = np.array(self.coverage_curve)
        first = curve[: min(50, len(curve))]
        slope = (
            float(stats.linregress(np.arange(len(first)), first).slope) if len(first) >= 2 else 0.0
        )
        finite_sep = [s for s in self.min_separation_curve if math.isfinite(s)]
        returned = self.returned()
        sc = self.scenario
        result = {
            "scenario": sc.name,
            "algorithm": algorithm,
            "seed": int(seed),
            "steps": max(int(self.steps) - 1, 0),  # records are the start plus one per step
            "coverage": float(curve[-1]) if len(curve) else 0.0,
            "coverage_curve": [round(float(c), 6) for c in curve],
            "coverage_slope_50": slope,
            "engaged_count": len(self.engagements),
            "engaged_value": float(sum(e["value"] for e in self.engagements)),
            "engaged_curve": list(self.engaged_curve),
            "engage_misses": int(self.engage_misses),
            "decision_modes": {m: int(c) for m, c in zip(MODES, self.mode_steps, strict=True)},
            "turned_home_at_start": self.turned_home_at_start,
            "min_separation_km": float(min(finite_sep)) if finite_sep else None,
            "min_separation_curve": [
                None if not math.isfinite(s) else round(s, 4) for s in self.min_separation_curve
            ],
            "mean_min_separation_curve": [
                None if not math.isfinite(s) else round(s, 4)
                for s in self.mean_min_separation_curve
            ],
            "returned_count": int(returned.sum()),
            "violations": dict(self.violations),
            # C_t and C_c judged at decision instants and on the straight legs between them (the
            # paper's grid); a MAVLink run adds the flown tracks' account ("track_audit")
            "violations_measured_at": "decision steps",
            "wall_time_s": float(wall_time_s),
            "uav_count": self.n,
            "min_separation_limit_km": sc.config.min_separation_km,
            "max_turn_deg": sc.config.max_turn_deg,  # phi_max, the turn rule judged
            "max_range_km": sc.config.max_range_km
            if math.isfinite(sc.config.max_range_km)
            else None,
            "origin": {
                "lat": sc.origin.lat_deg,
                "lon": sc.origin.lon_deg,
                "alt_m": sc.origin.alt_m,
            },
            "altitude_m": sc.altitude_m,
            "area_km": list(sc.config.area_km),
            "threats": [
                {"x_km": t.x_km, "y_km": t.y_km, "radius_km": t.radius_km} for t in sc.threats
            ],
            "targets": [
                {"id": t.id, "kind": t.kind, "x_km": t.x_km, "y_km": t.y_km, "value": t.value}
                for t in sc.targets
            ],
            "engagements": list(self.engagements),
            "uavs": [
                {
                    "id": i + 1,
                    "start_km": [float(self.starts[i, 0]), float(self.starts[i, 1])],
                    "track_km": self.tracks[i],
                    "planned_km": self.planned[i],
                    "distance_km": round(float(self.distance_km[i]), 4),
                    "returned": bool(returned[i]),
                }
                for i in range(self.n)
            ],
        }
        if extra:
            result.update(extra)
        return result


def format_summary(result: dict) -> str:
    """The lines a person reads first of a result (``MissionRecorder.result``), for every
    command that prints one (``run``, ``demo``, ``daemon``)."""
    v = result["violations"]
    sep = result["min_separation_km"]
    return "\n".join([
        f"scenario {result['scenario']}  algorithm {result['algorithm']}  seed {result['seed']}"
        f"  steps {result['steps']}",
        f"coverage        {100 * result['coverage']:.1f} %"
        f"  (slope over the first 50 steps {100 * result['coverage_slope_50']:.3f} %/step)",
        f"engaged         {result['engaged_count']} targets, value {result['engaged_value']:g}",
        f"min separation  {'n/a' if sep is None else f'{sep:.2f} km'}",
        _home_line(result),
        *_turned_home_lines(result),
        f"violations      threat {v['threat']}, separation {v['separation']}, turn {v['turn']},"
        f" range {v['range']} (at decision steps)",
        *_continuous_lines(result),
        f"wall time       {result['wall_time_s']:.2f} s",
    ])  # fmt: skip


def _home_line(result: dict) -> str:
    """UAVs at home (within a cell of their start) at the last decision step. Over MAVLink the
    daemon sends RTL only after that step, so a low count there is the mission's end, not a
    failed return."""
    line = (
        f"at home         {result['returned_count']} of {result['uav_count']} at the last "
        f"decision step"
    )
    return line + ("; RTL sent after it" if result.get("source") == "mavlink" else "")


def turned_home_warning(steps: int) -> str:
    """What every UAV turning home at the first step means (``turned_home_at_start``)."""
    return (
        f"every UAV turned home at the first step: with home_by_end, {steps} steps leave no "
        "time to go out and back with the steps kept in reserve; fly more steps (swarmplan "
        "run --as-flown --steps N shows what a flown mission of N steps does) or set "
        "home_by_end = false"
    )


def _turned_home_lines(result: dict) -> list[str]:
    """A warning when every UAV turned home at the first step (``home_by_end``)."""
    if not result.get("turned_home_at_start"):
        return []
    return [f"warning         {turned_home_warning(result['steps'])}"]


def _continuous_lines(result: dict) -> list[str]:
    """The safety account along every position report (``track_audit``, a MAVLink run) and the
    simulator's own ground truth (``simulator_truth``), when the result has them."""

    def km(value: float | None) -> str:
        return "n/a" if value is None else f"{value:.2f} km"

    lines = []
    audit = result.get("track_audit")
    if audit:
        for name, f in [("all", audit["all"]), *audit["phases"].items()]:
            lines.append(
                f"  along tracks  {name}: threat entries {f['threat_entries']}, separation "
                f"{f['separation_breaches']}, min separation {km(f['min_separation_km'])}, "
                f"min threat margin {km(f['min_threat_margin_km'])}"
            )
    truth = result.get("simulator_truth")
    if truth:
        lines.append(
            f"  simulator     threat entries {truth['threat_entries']}, separation "
            f"{truth['separation_breaches']}, min separation {km(truth['min_separation_km'])}, "
            f"min threat margin {km(truth['min_threat_margin_km'])}"
        )
    return lines
