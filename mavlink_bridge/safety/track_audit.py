"""Safety measured from every position report, not only at decision instants.

The mission recorder (``planner.metrics.MissionRecorder``) judges the constraints C_t
(threats) and C_c (separation, d_min) at decision instants and on the straight legs between
them, as the paper's grid does. A plane flies between those instants, circles in a failsafe and
flies home after the mission: two planes can pass 0.9 km apart between two decisions that both
measured 1.3 km (issue 12, finding 1). This module judges the whole flight from every
GLOBAL_POSITION_INT the vehicles sent:

* each vehicle's track is its reports in the order of its own clock, joined by straight
  segments (a 100 m/s plane turning at 5.6 deg/s strays ~30 m from a 5 s chord). Two reports
  more than ``max_gap_s`` apart are not joined: that stretch is counted as unobserved;
* **threat** (C_t): along every segment, the distance to every threat circle's edge
  (``planner.constraints.segment_clearance``, exact for a straight segment); an *entry* is a
  run of consecutive segments inside one or more circles;
* **separation** (C_c): every pair of tracks is put on a common time base (the union of both
  vehicles' report instants, each track linearly interpolated), and on each interval between
  two such instants, where both move linearly, the exact closest approach; a *breach* is a run of
  intervals closer than d_min.

Every segment and interval belongs to a **phase**: ``launch`` (take-off), ``mission`` (the
decision loop, at and between decisions), ``hold`` (the daemon holding the vehicles at safe
points because it could not keep up), ``failsafe`` (a vehicle out of GUIDED or in a failsafe
during the mission: CIRCLE, RTL after a fence breach, a GCS failsafe) and ``rtl`` (the final
return). Each phase is reported on its own, and all together.

Clocks: the reports carry each vehicle's ``time_boot_ms``. Vehicles of one simulator share one
clock; separate autopilots (SITL instances, aircraft) booted at different times, and their
clocks drift apart: SITL instances on a loaded machine run below their speedup by different
amounts (5 ArduPlane SITL planes at 10x, load average 11-15: 58-310 s behind 10x the wall
clock after ~65 min of their clocks, up to 250 s apart). Each vehicle's offset to the daemon's
clock is estimated, over every ``drift_window_s`` of its clock, as the smallest (arrival time
x time scale - report time) of its reports there (the least-delayed report), and followed
piecewise linearly between windows.
Vehicles whose offsets agree within ``shared_clock_tolerance_s`` (the median over the windows of
the largest disagreement) are taken as one shared clock (a simulator, or lockstep, where wall
time says nothing). A single offset per vehicle, the smallest over the whole flight, took the
drifting SITL clocks for one shared clock: planes 1.8 km apart at every instant were judged on
reports a minute apart, 0.74 km apart (a separation breach that never happened).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mavlink_bridge.vehicles.autopilot_adapter import autopilot_for
from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_wire.protocol import mavlink
from planner.constraints import segment_clearance

#: phases in the order a segment shared by two of them is reported under (most telling first)
PHASES = ("failsafe", "hold", "rtl", "launch", "mission")


@dataclass
class _Track:
    """The accepted reports of one vehicle."""

    t_s: list[float] = field(default_factory=list)  # the vehicle's clock, seconds
    x_km: list[float] = field(default_factory=list)
    y_km: list[float] = field(default_factory=list)
    phase: list[int] = field(default_factory=list)  # index into PHASES
    #: per report: arrival wall x time scale - report time (NaN: no arrival time)
    arrival_offsets_s: list[float] = field(default_factory=list)


@dataclass
class PhaseFigures:
    """What one phase (or the whole flight) measured."""

    threat_entries: int = 0
    min_threat_margin_km: float = math.inf  # distance to the nearest threat edge (< 0: inside)
    separation_breaches: int = 0
    min_separation_km: float = math.inf
    closest_pair: tuple[int, int] | None = None  # UAV indices (0-based)
    closest_at_s: float | None = None  # vehicle clock of the closest approach
    observed_s: float = 0.0  # summed over vehicles: time covered by joined segments

    def as_dict(self) -> dict:
        def km(v: float) -> float | None:
            return None if not math.isfinite(v) else round(float(v), 4)

        return {
            "threat_entries": self.threat_entries,
            "min_threat_margin_km": km(self.min_threat_margin_km),
            "separation_breaches": self.separation_breaches,
            "min_separation_km": km(self.min_separation_km),
            "closest_pair_uavs": None if self.closest_pair is None else list(self.closest_pair),
            "closest_at_s": None if self.closest_at_s is None else round(self.closest_at_s, 2),
            "observed_uav_s": round(self.observed_s, 1),
        }


def closest_approach(r0: np.ndarray, r1: np.ndarray) -> np.ndarray:
    """Smallest |r(s)| for s in [0, 1] of the relative positions moving linearly from ``r0`` to
    ``r1`` (..., 2): the closest approach of two planes that both fly straight on an interval."""
    dr = r1 - r0
    denom = np.sum(dr * dr, axis=-1)
    s = np.clip(-np.sum(r0 * dr, axis=-1) / np.maximum(denom, 1e-18), 0.0, 1.0)
    s = np.where(denom > 0, s, 0.0)
    closest = r0 + s[..., None] * dr
    return np.hypot(closest[..., 0], closest[..., 1])


def _runs(flags: np.ndarray, joined: np.ndarray) -> np.ndarray:
    """Start of each run of True ``flags`` (a flag whose predecessor is False or not joined to it:
    ``joined[k]`` says item k continues item k - 1)."""
    before = np.concatenate([[False], flags[:-1]]) & joined
    return flags & ~before


class TrackAudit:
    """Collects every position report of a mission and judges C_t and C_c along the tracks."""

    def __init__(
        self,
        n: int,
        threat_xy_km: np.ndarray,
        threat_radius_km: np.ndarray,
        min_separation_km: float,
        max_gap_s: float = 10.0,
        shared_clock_tolerance_s: float = 1.0,
        drift_window_s: float = 30.0,
        project: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
    ) -> None:
        """``project``: the reports are (lat, lon) degrees, turned into the mission frame (km)
        in one vectorised call when judged (a geodesic per report would cost ~3 ms each)."""
        self.n = n
        self.threat_xy = np.asarray(threat_xy_km, float).reshape(-1, 2)
        self.threat_r = np.asarray(threat_radius_km, float).reshape(-1)
        self.min_separation_km = float(min_separation_km)
        self.max_gap_s = float(max_gap_s)
        self.shared_clock_tolerance_s = float(shared_clock_tolerance_s)
        self.drift_window_s = float(drift_window_s)
        self.project = project
        self.tracks = [_Track() for _ in range(n)]
        self.phase = "launch"
        #: phase changes on each vehicle's clock: (its newest report time at the change, phase)
        self.changes: list[tuple[np.ndarray, str]] = []
        self.latest_s = np.full(n, -math.inf)  # each vehicle's newest report time taken in
        self.reports = 0
        self.closed = False  # after end(): the account is the mission's, nothing more is added

    def set_phase(self, phase: str) -> None:
        """The daemon's phase from now on (``launch``, ``mission``, ``hold``, ``rtl``). A report
        belongs to the phase in force at its own time: one stamped no later than its vehicle's
        newest report taken in before the change belongs to the phase before, however late it
        arrives (in lockstep a grant's reports arrive whenever the machine gets to them)."""
        if phase not in PHASES:
            raise ValueError(f"unknown phase {phase!r}")
        self.phase = phase
        self.changes.append((self.latest_s.copy(), phase))

    def phase_at(self, uav: int, t_s: float) -> str:
        """The phase in force at time ``t_s`` of vehicle ``uav``'s clock."""
        for at_s, phase in reversed(self.changes):
            if t_s > at_s[uav]:
                return phase
        return "launch"

    def end(self) -> None:
        """The mission's account is complete (the daemon's watch of the flight home is over):
        later reports are not added. A lockstep simulator runs free once released, and how
        many of its reports arrive before the link closes depends on the machine's speed."""
        self.closed = True

    def add(
        self,
        uav: int,
        t_s: float,
        xy_km: tuple[float, float] | np.ndarray,
        arrival_scaled_s: float | None = None,
        in_failsafe: bool = False,
    ) -> None:
        """One position report of ``uav`` at its clock ``t_s``; ``arrival_scaled_s`` is when it
        arrived (wall seconds x time scale, for the clock offsets); ``in_failsafe`` marks a
        vehicle the daemon is not flying right now (out of GUIDED, or in a failsafe)."""
        if self.closed or not 0 <= uav < self.n or not math.isfinite(t_s):
            return
        track = self.tracks[uav]
        phase = self.phase_at(uav, t_s)
        self.latest_s[uav] = max(self.latest_s[uav], float(t_s))
        if in_failsafe and phase in ("mission", "hold"):
            phase = "failsafe"
        track.t_s.append(float(t_s))
        track.x_km.append(float(xy_km[0]))
        track.y_km.append(float(xy_km[1]))
        track.phase.append(PHASES.index(phase))
        offset = math.nan if arrival_scaled_s is None else arrival_scaled_s - t_s
        track.arrival_offsets_s.append(float(offset))
        self.reports += 1

    # ------------------------------------------------------------------ judging

    def _offset_knots(self, uav: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Vehicle ``uav``'s clock offset, per ``drift_window_s`` of its clock: the report there
        with the smallest arrival offset (its time, that offset); None without arrival times."""
        tr = self.tracks[uav]
        t = np.asarray(tr.t_s, float)
        off = np.asarray(tr.arrival_offsets_s, float)
        known = np.isfinite(off)
        if not known.any():
            return None
        t, off = t[known], off[known]
        window = np.floor((t - t.min()) / self.drift_window_s).astype(np.int64)
        order = np.lexsort((off, window))  # by window, then offset: each window's least first
        first = order[np.concatenate([[True], np.diff(window[order]) != 0])]
        first = first[np.argsort(t[first], kind="stable")]
        return t[first], off[first]

    def clock_offsets(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per vehicle: (knot times on its clock, seconds to add there) to reach the common time
        base, followed linearly between knots; all zero for one shared clock."""
        zero = (np.zeros(1), np.zeros(1))
        knots = [self._offset_knots(i) for i in range(self.n)]
        known = [k for k in knots if k is not None]
        if not known:
            return [zero] * self.n
        reference = float(np.median([k[1].min() for k in known]))
        shifted = [zero if k is None else (k[0], k[1] - reference) for k in knots]
        # do the offsets agree at the knots' instants (each vehicle's curve read there)?
        at = np.unique(np.concatenate([k[0] for k in known]))
        curves = np.array([np.interp(at, k[0], k[1]) for k in known])
        disagreement = np.abs(curves - np.median(curves, axis=0)).max(axis=0)
        if float(np.median(disagreement)) <= self.shared_clock_tolerance_s:
            return [zero] * self.n  # one shared clock (a simulator): no correction
        return shifted

    def _arrays(self, uav: int, offset: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, ...]:
        tr = self.tracks[uav]
        t = np.asarray(tr.t_s, float)
        t = t + np.interp(t, offset[0], offset[1])
        order = np.argsort(t, kind="stable")
        t = t[order]
        a, b = np.asarray(tr.x_km, float)[order], np.asarray(tr.y_km, float)[order]
        if self.project is not None and len(a):
            a, b = self.project(a, b)
        xy = np.stack([np.asarray(a, float), np.asarray(b, float)], 1)
        phase = np.asarray(tr.phase, np.int64)[order]
        keep = np.concatenate([[True], np.diff(t) > 0]) if len(t) else np.zeros(0, bool)
        return t[keep], xy[keep], phase[keep]

    def summary(self) -> dict:
        """The figures of every phase and of the whole flight (``result["track_audit"]``)."""
        offsets = self.clock_offsets()
        figures = {name: PhaseFigures() for name in PHASES}
        overall = PhaseFigures()
        tracks = [self._arrays(i, offsets[i]) for i in range(self.n)]
        unobserved = 0.0
        for t, xy, phase in tracks:
            if len(t) == 0:
                continue
            dt = np.diff(t)
            joined = dt <= self.max_gap_s
            unobserved += float(dt[~joined].sum())
            # items: the first report (a point), then each interval to the next report: a
            # segment where joined, else that next report alone (a point)
            if len(self.threat_r):
                point = segment_clearance(xy, xy, self.threat_xy, self.threat_r)
                seg = segment_clearance(xy[:-1], xy[1:], self.threat_xy, self.threat_r)
                clear = np.concatenate([point[:1], np.where(joined, seg, point[1:])])
                continues = np.concatenate([[False], joined])
                entries = _runs(clear < 0, continues)
                self._add_threats(clear, entries, phase, figures, overall)
            for k, name in enumerate(PHASES):
                covered = float(dt[joined & (phase[1:] == k)].sum())
                figures[name].observed_s += covered
                overall.observed_s += covered
        for i in range(self.n):
            for j in range(i + 1, self.n):
                self._judge_pair(i, j, tracks[i], tracks[j], figures, overall)
        out = {
            "source": "every position report (GLOBAL_POSITION_INT), tracks interpolated",
            "reports": int(sum(len(t) for t, _, _ in tracks)),  # distinct instants
            "max_gap_s": self.max_gap_s,
            "unobserved_uav_s": round(unobserved, 1),
            "clock_offsets_s": [round(float(np.median(o[1])), 3) for o in offsets],
            # how far each clock drifted from the common base over the flight (s)
            "clock_drift_s": [round(float(o[1][-1] - o[1][0]), 3) for o in offsets],
            "all": overall.as_dict(),
            "phases": {
                name: figures[name].as_dict() for name in PHASES if figures[name].observed_s > 0
            },
        }
        return out

    @staticmethod
    def _add_threats(
        clear: np.ndarray,
        entries: np.ndarray,
        phase: np.ndarray,
        figures: dict[str, PhaseFigures],
        overall: PhaseFigures,
    ) -> None:
        for k, name in enumerate([*PHASES, None]):
            mine = np.ones(len(clear), bool) if name is None else phase == k
            if not mine.any():
                continue
            f = overall if name is None else figures[name]
            f.threat_entries += int(np.count_nonzero(entries & mine))
            f.min_threat_margin_km = min(f.min_threat_margin_km, float(clear[mine].min()))

    def _judge_pair(
        self,
        i: int,
        j: int,
        a: tuple[np.ndarray, ...],
        b: tuple[np.ndarray, ...],
        figures: dict[str, PhaseFigures],
        overall: PhaseFigures,
    ) -> None:
        ta, xa, pa = a
        tb, xb, pb = b
        if len(ta) < 2 or len(tb) < 2:
            return
        lo, hi = max(ta[0], tb[0]), min(ta[-1], tb[-1])
        if hi <= lo:
            return
        t = np.union1d(ta[(ta >= lo) & (ta <= hi)], tb[(tb >= lo) & (tb <= hi)])
        t = np.union1d(t, [lo, hi])

        def at(ts: np.ndarray, xy: np.ndarray, ph: np.ndarray) -> tuple[np.ndarray, ...]:
            pos = np.stack([np.interp(t, ts, xy[:, 0]), np.interp(t, ts, xy[:, 1])], 1)
            # the report interval each common interval lies in: joined and of which phase
            k = np.clip(np.searchsorted(ts, t[1:], side="left"), 1, len(ts) - 1)
            ok = (ts[k] - ts[k - 1]) <= self.max_gap_s
            return pos, ok, ph[k]

        pos_a, ok_a, ph_a = at(ta, xa, pa)
        pos_b, ok_b, ph_b = at(tb, xb, pb)
        rel = pos_a - pos_b
        d = closest_approach(rel[:-1], rel[1:])
        ok = ok_a & ok_b
        if not ok.any():
            return
        phase = np.minimum(ph_a, ph_b)  # PHASES is ordered most telling first
        close = (d < self.min_separation_km - 1e-9) & ok
        breaches = _runs(close, np.concatenate([[False], ok[1:] & ok[:-1]]))
        d = np.where(ok, d, np.inf)
        for k, name in enumerate([*PHASES, None]):
            mine = np.ones_like(ok) if name is None else phase == k
            if not mine.any():
                continue
            f = overall if name is None else figures[name]
            f.separation_breaches += int(np.count_nonzero(breaches & mine))
            dm = np.where(mine, d, np.inf)
            m = int(np.argmin(dm))
            if dm[m] < f.min_separation_km:
                f.min_separation_km = float(dm[m])
                f.closest_pair = (i, j)
                f.closest_at_s = float(t[m])


def position_listener(
    audit: TrackAudit,
    time_scale: float | None,
    index_of: Callable[[VehicleKey], int] = lambda key: key.system_id - 1,
) -> Callable[[VehicleState, mavlink.MAVLink_message], None]:
    """A ``SwarmLink`` listener feeding ``audit`` (made with a ``project`` from degrees) every
    GLOBAL_POSITION_INT a vehicle's state took in (not one dropped as stale or implausible)
    while it flies (1 m above home). A vehicle out of GUIDED (TAKEOFF aside: its mode
    as last heard may lag its first guided seconds) or reporting CRITICAL (a failsafe, a fence
    breach) counts under ``failsafe`` during the mission. ``time_scale`` None: one shared clock
    (lockstep). ``index_of``: the audit's index of a vehicle's (link, system id)."""

    def listen(v: VehicleState, msg: mavlink.MAVLink_message) -> None:
        if msg.get_type() != "GLOBAL_POSITION_INT" or msg.get_srcComponent() != 1:
            return
        if not v.has_position or v.time_boot_ms != msg.time_boot_ms or v.lat_deg != msg.lat * 1e-7:
            return
        if v.relative_alt_m < 1.0:  # (not v.armed: the heartbeat saying so may come later)
            return
        failsafe = (
            not autopilot_for(v).flown(v.custom_mode)
            or v.system_status == mavlink.MAV_STATE_CRITICAL
        )
        arrival = None if time_scale is None else time.monotonic() * time_scale
        where = (v.lat_deg, v.lon_deg)  # the audit projects them all at once (``project``)
        audit.add(index_of(v.key), v.time_boot_ms / 1e3, where, arrival, failsafe)

    return listen
