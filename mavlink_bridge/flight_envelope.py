"""The flight-path layer of the safety envelope: judge the path each plane will really fly.

The cell-level envelope (``safety_envelope.py``) checks the planner's next cells. A plane does
not fly cell centres: it turns on a ~1 km radius (more when it flies faster), lags after turns
and circles a point it reaches. So before a guided target is sent, the daemon predicts the
flown path (``flight_prediction.py``) over ``horizon_steps`` decision steps (three by
default: long enough to reach a target two legs ahead, whatever the step's length) and
accepts a target only if

* the predicted path, and the chord between its positions at the decision instants (what the
  result's threat count measures), keeps ``threat_margin_km`` clear of every threat circle;
* so does the loiter circle around the target: a plane that gets no newer target circles
  there, so every accepted target leaves a safe way on (the "keep going" candidate below).
  The plane arrives flying straight at the target and turns onto its circle only after
  passing it, so the circle is judged out to a loiter diameter from the target
  (``PlaneModel.loiter_reach_km``; with the radius alone, planes whose ground station went
  silent for 3 s at 20x entered threat zones in 7 of 10 runs, issue 12);
* at every predicted second of the next ``separation_horizon_steps`` it stays
  ``min_separation_km + separation_margin_km`` from the predicted path of every UAV already
  settled this step (beyond the next decision every plane gets a new target); and so it does
  when, from the next decision instant on, every plane flew straight on for the time it needs
  to turn away (a quarter circle at its bank limit and fastest speed, ``escape_s``): the new
  target cannot turn a plane at once. Without this, two planes converging at 100-150 m/s
  with their targets 1 km apart were accepted (1.32 km apart within 1.5 steps), and one step
  later nothing was left that kept them apart: 0.63 km along the tracks in the lockstep demo
  (paper-10uav seed 2), where judging the whole 3-step prediction had kept 1.56 km. In paced
  time the same holds for the paths a lossy link may fly (a lost airspeed, a target resent
  until late: ``_lossy_link_paths``), every variant of a plane against every variant of the
  others, wherever some candidate can keep it; where none can, the prediction decides.

Paths are predicted from each plane's measured speed, at the airspeed it will be sent for the
leg (``leg_timing``: the leg to the candidate's cell in one decision step, see
``flight_prediction.leg_speed_mps``; the keep-going and circle-here fallbacks at cruise speed),
and the loiter circle is the one flown at that airspeed.

Candidates, in order: the cell-level envelope's choice; with leg timing, the same cell at cruise
speed (a slower plane turns and circles tighter: near a threat the planner's cell is kept and
flown late rather than replaced, and that is not counted as a replacement); the other cells
reachable within phi_max that pass the cell-level rules, those with a safe way on
(``SafetyEnvelope.viable``) first, each group nearest the planner's cell first; the
target the plane already flies to (keep going); the centre of its current cell (circle here).
The first safe one is sent; when none is, the one that breaks the rules least. UAVs settle in
index order; one left without a safe candidate re-opens the choice of the settled UAV it comes
closest to (``_repair``). Replacements of the planner's cell are counted as
``predicted_threat`` / ``predicted_separation`` overrides.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mavlink_bridge.flight_prediction import PlaneModel, leg_speed_mps, predict_paths
from mavlink_bridge.safety_envelope import SafetyEnvelope
from planner.constraints import segment_clearance
from planner.grid import HEADING_STEPS, heading_of_angle, turn_options


@dataclass
class FlightChoice:
    """The guided target and airspeed of every UAV and the cell/heading it stands for."""

    aims_km: np.ndarray  # (N, 2)
    next_cells: np.ndarray  # (N, 2)
    next_headings: np.ndarray  # (N,)
    speeds_mps: np.ndarray  # (N,) airspeed to fly the leg at
    overrides: dict[str, int] = field(default_factory=dict)
    min_separation_km: float = np.inf  # predicted, between the accepted paths
    #: the same over every lossy-link variant of each (paced time; as predicted in lockstep)
    min_separation_lossy_km: float = np.inf


@dataclass
class LossyLinkPaths:
    """Candidates' paths as a lossy link may deliver their commands (V variants, M candidates,
    one sample a second; ``FlightEnvelope._lossy_link_paths``)."""

    from_command: np.ndarray  # (V, M, S + 1, 2) from where the command takes hold
    #: (V, M, S + 1, 2) from now, the same instants as the prediction; None without a command
    #: delay (lockstep: separation is judged on the prediction alone)
    from_now: np.ndarray | None


@dataclass
class _Candidate:
    cell: np.ndarray
    heading: int
    aim: np.ndarray
    derived: bool = False  # cell/heading come from the predicted path (keep / circle)
    cruise: bool = False  # flown at cruise speed even with leg timing (a slower, tighter try)


@dataclass(frozen=True)
class FlightEnvelope:
    """Chooses each plane's guided target from its predicted flight path."""

    cells: SafetyEnvelope
    model: PlaneModel
    step_s: float = 10.0
    #: how far ahead paths are predicted, in decision steps (a horizon in seconds would not
    #: cover one step of a scenario with longer steps)
    horizon_steps: float = 3.0
    #: the planes' paths are kept apart over this many decision steps of the prediction: at the
    #: next decision every plane gets a new target, so the predicted circles around this step's
    #: targets beyond it are not what will be flown. Judged over all three steps, two ArduPlane
    #: SITL planes whose targets were a cell or two apart were held circling (a hold is a turn
    #: of the whole circle): 9 holds and 2-3 turn breaks in 16 steps, 1 and 1 with 1.5 steps
    separation_horizon_steps: float = 1.5
    threat_margin_km: float = 0.25
    separation_margin_km: float = 0.3
    leg_timing: bool = True  # airspeed per leg, so each leg takes one step (flight_prediction)
    #: judge separation also on the planes flying straight on from the next decision instant
    #: for ``escape_s`` (see the module docstring)
    separation_escape: bool = True
    #: also keep clear the circle a plane would fly where it is (a failsafe or RC loss that
    #: switches it to CIRCLE) at every predicted second of the coming decision period
    failsafe_circle: bool = True
    #: paced time: how late (s of the vehicles' clock) a guided target may reach its plane (a
    #: lost command is resent until the step's deadline, ``pacing.STEP_DEADLINE_SHARE`` of a
    #: period); meanwhile the plane flies on to its previous target. 0 in lockstep (the
    #: simulated time waits for the commands)
    command_delay_s: float = 0.0

    @property
    def escape_s(self) -> float:
        """Seconds a plane at its fastest needs to turn a quarter circle at its bank limit: how
        long a new target takes to turn it away from where it was heading (24 s at 150 m/s and
        45 deg; 2 s for ArduPlane's 30 m/s and 65 deg)."""
        return float(np.pi / 2 / self.model.turn_rate_radps(self.model.max_speed_mps))

    @property
    def horizon_s(self) -> float:
        """Prediction horizon (s): ``horizon_steps`` decision steps, at least one."""
        return max(1.0, self.horizon_steps) * self.step_s

    def choose(
        self,
        positions_km: np.ndarray,
        courses_rad: np.ndarray,
        speeds_mps: np.ndarray,
        cells: np.ndarray,
        headings: np.ndarray,
        proposed_cells: np.ndarray,
        proposed_headings: np.ndarray,
        previous_aims_km: np.ndarray,
        flown_km: np.ndarray,
        home_km: np.ndarray,
        active: np.ndarray,
        lead: float,
        decision_positions_km: np.ndarray | None = None,
        elapsed_s: np.ndarray | None = None,
    ) -> FlightChoice:
        """Guided targets for every UAV at ``positions_km`` flying at ``speeds_mps`` now
        (inactive ones keep the proposal; nothing is sent). In paced time a plane is
        ``elapsed_s`` past the decision instant, when it was at ``decision_positions_km`` (where
        the measured chord to the next decision instant starts); by default it is there now."""
        grid = self.cells.grid
        n = len(cells)
        if decision_positions_km is None:
            decision_positions_km = positions_km
        elapsed = np.zeros(n) if elapsed_s is None else np.asarray(elapsed_s, dtype=float)
        candidates: list[list[_Candidate]] = []
        for i in range(n):
            candidates.append(
                self._candidates(
                    cells[i],
                    int(headings[i]),
                    proposed_cells[i],
                    int(proposed_headings[i]),
                    previous_aims_km[i],
                    float(flown_km[i]),
                    home_km[i],
                    lead,
                )
                if active[i]
                else []
            )
        rows = [(i, k) for i in range(n) for k in range(len(candidates[i]))]
        aims = np.array([candidates[i][k].aim for i, k in rows]).reshape(-1, 2)
        starts = np.array([positions_km[i] for i, _ in rows]).reshape(-1, 2)
        speeds_now = np.array([speeds_mps[i] for i, _ in rows], dtype=float)
        commanded = np.full(len(rows), self.model.speed_mps)
        if self.leg_timing and rows:  # a cell's leg in one step; keep going / circle: cruise
            leg_from = grid.centre_km(np.array([cells[i] for i, _ in rows]))
            leg_to = grid.centre_km(np.array([candidates[i][k].cell for i, k in rows]))
            untimed = np.array(
                [candidates[i][k].derived or candidates[i][k].cruise for i, k in rows]
            )
            timed = leg_speed_mps(self.model, starts, leg_from, leg_to, speeds_now, self.step_s)
            commanded = np.where(untimed, commanded, timed)
        paths = predict_paths(
            self.model,
            starts,
            np.array([courses_rad[i] for i, _ in rows]),
            aims,
            self.horizon_s,
            speed_mps=speeds_now,
            commanded_mps=commanded,
        )
        row_uav = np.array([i for i, _ in rows], dtype=np.int64)
        # judged for threats (when there are any) and, paced, for separation: not predicted
        # when neither needs it (lockstep among no threats)
        paced = round(self.command_delay_s) >= 1  # as ``_lossy_link_paths`` counts it
        threats = len(self.cells.threat_radius_km) > 0
        lossy = (
            self._lossy_link_paths(
                positions_km, courses_rad, speeds_mps, previous_aims_km, row_uav, aims, commanded
            )
            if rows and (threats or paced)
            else None
        )
        # (M, V, T, 2): the instants each candidate is kept apart at, as predicted and, in paced
        # time, as each lossy-link variant flies it (a late or lost command)
        kept_apart = self._separation_paths(paths)[:, None]
        if lossy is not None and lossy.from_now is not None:
            variants = [self._separation_paths(v) for v in lossy.from_now]
            kept_apart = np.stack([kept_apart[:, 0], *variants], axis=1)
        clearance = np.minimum(
            self._threat_clearance(
                paths,
                np.asarray(decision_positions_km, dtype=float)[row_uav].reshape(-1, 2),
                elapsed[row_uav],
            ),
            self._loiter_clearance(aims, np.maximum(speeds_now, commanded)),
        )
        if lossy is not None and threats:
            flown = lossy.from_command.reshape(-1, *lossy.from_command.shape[2:])
            clearance = np.minimum(
                clearance,
                self._polyline_clearance(flown).reshape(len(lossy.from_command), -1).min(axis=0),
            )
        if self.failsafe_circle:
            clearance = np.minimum(
                clearance, self._failsafe_circle_clearance(paths, np.maximum(speeds_now, commanded))
            )
        row_of = {key: r for r, key in enumerate(rows)}
        out_aims = grid.centre_km(proposed_cells)
        out_speeds = np.full(n, self.model.speed_mps)
        out_cells = np.array(proposed_cells, dtype=np.int64, copy=True)
        out_headings = np.array(proposed_headings, dtype=np.int64, copy=True)
        overrides = {"predicted_threat": 0, "predicted_separation": 0}
        need_sep = self.cells.min_separation_km + self.separation_margin_km
        threat_ok = clearance >= self.threat_margin_km
        # kept apart as a lossy link may fly them where some candidate can be; where none can
        # (two planes whose last legs already close within the delay), as predicted
        nominal = kept_apart[:, :1]
        tiers = [kept_apart, nominal] if kept_apart.shape[1] > 1 else [nominal]
        chosen: dict[int, int] = {}  # UAV -> candidate index, settled in index order
        for i in range(n):
            if not candidates[i]:
                continue
            for apart in tiers:
                others = [apart[row_of[(j, k)]] for j, k in chosen.items()]
                best: tuple[float, int] | None = None
                for k in range(len(candidates[i])):
                    r = row_of[(i, k)]
                    sep = self._separation(apart[r], others)
                    if threat_ok[r] and sep >= need_sep:
                        best = (np.inf, k)
                        break
                    score = min(clearance[r] - self.threat_margin_km, sep - need_sep)
                    if best is None or score > best[0]:
                        best = (score, k)
                assert best is not None
                chosen[i] = best[1]
                if not np.isfinite(best[0]) or self._repair(
                    i, chosen, candidates, apart, row_of, threat_ok, need_sep
                ):
                    break
        for i, k in chosen.items():
            r = row_of[(i, k)]
            kept = k == 1 and candidates[i][1].cruise  # the planner's cell, only flown slower
            if k != 0 and not kept:
                first = row_of[(i, 0)]
                overrides["predicted_separation" if threat_ok[first] else "predicted_threat"] += 1
            cand = candidates[i][k]
            path = paths[r]
            out_aims[i] = cand.aim
            out_speeds[i] = commanded[r]
            if cand.derived:
                last = len(path) - 1  # samples are one second apart
                per_step = min(max(1, round(self.step_s)), last)
                end, before = path[per_step], path[per_step - 1]
                out_cells[i] = grid.cell_of(end)
                move = end - before
                out_headings[i] = (
                    int(heading_of_angle(np.arctan2(move[1], move[0])))
                    if np.any(move)
                    else int(headings[i])
                )
            else:
                out_cells[i], out_headings[i] = cand.cell, cand.heading

        def closest(apart: np.ndarray) -> float:
            accepted = [apart[row_of[(i, k)]] for i, k in chosen.items()]
            return min(
                (self._separation(path, accepted[a + 1 :]) for a, path in enumerate(accepted)),
                default=np.inf,
            )

        predicted = closest(nominal)
        as_flown = closest(kept_apart) if len(tiers) > 1 else predicted
        return FlightChoice(
            out_aims, out_cells, out_headings, out_speeds, overrides, predicted, as_flown
        )

    # ------------------------------------------------------------------ pieces

    def _repair(
        self,
        i: int,
        chosen: dict[int, int],
        candidates: list[list[_Candidate]],
        paths: np.ndarray,
        row_of: dict[tuple[int, int], int],
        threat_ok: np.ndarray,
        need_sep: float,
    ) -> bool:
        """UAV ``i`` found no safe candidate next to the UAVs settled before it. Re-open the
        choice of the settled UAV it comes closest to, ``j``: the first pair of candidates (j's
        in its order, then i's) that are both clear of threats, of every other settled UAV and
        of each other replaces both choices (True). Without such a pair nothing changes."""
        mine = paths[row_of[(i, chosen[i])]]
        rivals = [j for j in chosen if j != i]
        if not rivals:
            return False
        j = min(rivals, key=lambda o: self._separation(mine, [paths[row_of[(o, chosen[o])]]]))
        rest = [paths[row_of[(o, ko)]] for o, ko in chosen.items() if o not in (i, j)]
        safe_i = [
            k
            for k in range(len(candidates[i]))
            if threat_ok[row_of[(i, k)]]
            and self._separation(paths[row_of[(i, k)]], rest) >= need_sep
        ]
        for kj in range(len(candidates[j])):
            rj = row_of[(j, kj)]
            if not threat_ok[rj] or self._separation(paths[rj], rest) < need_sep:
                continue
            for ki in safe_i:
                if self._separation(paths[row_of[(i, ki)]], [paths[rj]]) >= need_sep:
                    chosen[i], chosen[j] = ki, kj
                    return True
        return False

    def _candidates(
        self,
        cell: np.ndarray,
        heading: int,
        proposed: np.ndarray,
        proposed_heading: int,
        previous_aim: np.ndarray,
        flown_km: float,
        home_km: np.ndarray,
        lead: float,
    ) -> list[_Candidate]:
        env = self.cells
        first = _Candidate(proposed, proposed_heading, env.aim_point_km(cell, proposed, lead))
        out = [first]
        if self.leg_timing:  # the planner's cell at cruise speed: a tighter turn and loiter
            out.append(_Candidate(first.cell, first.heading, first.aim, cruise=True))
        others = []
        for turn in turn_options(env.max_turn_deg):
            h = int((heading + turn) % 8)
            c = cell + HEADING_STEPS[h]
            if np.array_equal(c, proposed) or env.static_reason(cell, c, flown_km, home_km):
                continue
            others.append((not env.viable(c, h), float(np.hypot(*(c - proposed))), h, c))
        for *_, h, c in sorted(others, key=lambda t: t[:2]):
            out.append(_Candidate(c, h, env.aim_point_km(cell, c, lead)))
        if np.all(np.isfinite(previous_aim)):
            out.append(_Candidate(cell, heading, np.asarray(previous_aim, float), derived=True))
        out.append(_Candidate(cell, heading, env.grid.centre_km(cell), derived=True))
        return out

    def _lossy_link_paths(
        self,
        positions_km: np.ndarray,
        courses_rad: np.ndarray,
        speeds_mps: np.ndarray,
        previous_aims_km: np.ndarray,
        row_uav: np.ndarray,
        aims_km: np.ndarray,
        commanded_mps: np.ndarray,
    ) -> LossyLinkPaths:
        """Each candidate's path flown as a lossy link may deliver its commands: its
        DO_CHANGE_SPEED lost (the plane keeps the airspeed it flies now: at 150 m/s it turns on a
        2.29 km radius, not the 1.02 km of 100 m/s), and, in paced time, its DO_REPOSITION
        arriving ``command_delay_s`` late, after the plane flew on to its previous target
        meanwhile (each with and without the new airspeed). Predicted every second to the
        horizon from where the command takes hold (``from_command``: what the threat clearance
        judges; the stretch flown to the previous target before a late command is not counted,
        no choice of this step changes it) and from now, that stretch first
        (``from_now``: the instants separation is judged at)."""
        held = np.asarray(speeds_mps, dtype=float)[row_uav]
        starts = np.asarray(positions_km, dtype=float)[row_uav].reshape(-1, 2)
        courses = np.asarray(courses_rad, dtype=float)[row_uav]
        variants = [(starts, courses, held, held)]
        delay_s = round(self.command_delay_s)
        previous = np.asarray(previous_aims_km, dtype=float)
        on_way = None
        if delay_s >= 1:
            known = np.all(np.isfinite(previous), axis=1)
            on_way = predict_paths(
                self.model, positions_km, courses_rad, np.where(known[:, None], previous,
                np.asarray(positions_km, dtype=float)), delay_s, dt_s=0.5, speed_mps=speeds_mps,
            )[row_uav]  # fmt: skip
            late_xy = on_way[:, -1]
            move = on_way[:, -1] - on_way[:, -2]
            late_course = np.where(
                np.hypot(move[:, 0], move[:, 1]) > 0, np.arctan2(move[:, 1], move[:, 0]), courses
            )
            late_known = known[row_uav]
            late_starts = np.where(late_known[:, None], late_xy, starts)
            late_courses = np.where(late_known, late_course, courses)
            variants += [
                (late_starts, late_courses, held, commanded_mps),
                (late_starts, late_courses, held, held),
            ]
        m = len(aims_km)
        flown = predict_paths(
            self.model,
            np.concatenate([v[0] for v in variants]),
            np.concatenate([v[1] for v in variants]),
            np.tile(aims_km, (len(variants), 1)),
            self.horizon_s,
            dt_s=0.5,  # a clearance check: 2.8 deg of turn a step at 100 m/s is fine enough
            speed_mps=np.concatenate([v[2] for v in variants]),
            commanded_mps=np.concatenate([v[3] for v in variants]),
        ).reshape(len(variants), m, -1, 2)
        from_now = None
        if on_way is not None:  # the late ones: the stretch to the previous target first
            from_now = flown.copy()
            samples = flown.shape[2]
            late = np.concatenate([np.broadcast_to(on_way, (2, *on_way.shape)), flown[1:, :, 1:]],
                                  axis=2)[:, :, :samples]  # fmt: skip
            from_now[1:, late_known] = late[:, late_known]  # no previous target: from now
        return LossyLinkPaths(from_command=flown, from_now=from_now)

    def _loiter_clearance(self, aims_km: np.ndarray, speeds_mps: np.ndarray) -> np.ndarray:
        """Distance (km) from the loiter circle around each aim, flown at ``speeds_mps`` and
        entered as a plane does (``PlaneModel.loiter_reach_km``: a diameter from the aim), to the
        nearest threat edge."""
        env = self.cells
        if len(env.threat_radius_km) == 0:
            return np.full(len(aims_km), np.inf)
        d = np.hypot(*(aims_km[:, None, :] - env.threat_xy_km[None]).transpose(2, 0, 1))
        return (d - env.threat_radius_km[None]).min(axis=1) - self.model.loiter_reach_km(speeds_mps)

    def _failsafe_circle_clearance(self, paths: np.ndarray, speeds_mps: np.ndarray) -> np.ndarray:
        """Distance (km) to the nearest threat edge of the circle each plane would fly if, at any
        predicted second of the coming decision period (from 1 s on: where it is now no target
        changes), it were switched to circle where it is (the simulator's CIRCLE / LOITER: the
        vehicle's loiter radius around that point)."""
        env = self.cells
        if len(env.threat_radius_km) == 0:
            return np.full(len(paths), np.inf)
        last = int(min(paths.shape[1] - 1, max(1, round(self.step_s))))
        ahead = paths[:, 1 : last + 1]  # (M, K, 2)
        d = np.hypot(
            ahead[:, :, None, 0] - env.threat_xy_km[None, None, :, 0],
            ahead[:, :, None, 1] - env.threat_xy_km[None, None, :, 1],
        )
        edge = (d - env.threat_radius_km[None, None]).min(axis=(1, 2))
        return edge - self.model.loiter_radius_km(speeds_mps)

    def _threat_clearance(
        self, paths: np.ndarray, decision_km: np.ndarray, elapsed_s: np.ndarray
    ) -> np.ndarray:
        """Smallest distance (km) of each predicted path (sampled every second from now) to a
        threat edge: every predicted second, and the chords between the decision instants
        (what the result measures), the first from where the plane was at the last decision
        instant (``decision_km``, ``elapsed_s`` ago) to where it will be at the next."""
        if len(self.cells.threat_radius_km) == 0:
            return np.full(len(paths), np.inf)
        dense = self._polyline_clearance(paths)
        samples = paths.shape[1] - 1
        instants = self.step_s * np.arange(1, int(samples // self.step_s) + 1)  # s after it
        index = np.clip(np.round(instants[None] - elapsed_s[:, None]), 0, samples).astype(int)
        ahead = np.take_along_axis(paths, index[:, :, None], axis=1)
        marks = np.concatenate([decision_km[:, None], ahead], axis=1)
        if marks.shape[1] >= 2:
            dense = np.minimum(dense, self._polyline_clearance(marks))
        return dense

    def _polyline_clearance(self, points: np.ndarray) -> np.ndarray:
        """(M,) smallest distance (km) to a threat edge of each of M polylines (M, K, 2)."""
        env = self.cells
        return segment_clearance(
            points[:, :-1], points[:, 1:], env.threat_xy_km, env.threat_radius_km
        ).min(axis=1)

    def _separation_paths(self, paths: np.ndarray) -> np.ndarray:
        """The instants at which planes are kept apart, each column one instant for every row:
        the predicted paths over the first ``separation_horizon_steps`` decision steps, then
        (``separation_escape``) each plane flying straight on from where the prediction has it
        at the next decision instant, at its predicted velocity there, for ``escape_s``."""
        last = paths.shape[1] - 1
        upto = min(int(round(max(1.0, self.separation_horizon_steps) * self.step_s)), last)
        apart = paths[:, : upto + 1]
        if not self.separation_escape:
            return apart
        at = min(max(1, int(round(self.step_s))), last)
        velocity = paths[:, at] - paths[:, at - 1]  # km per second (samples are 1 s apart)
        ahead = np.arange(1, int(np.ceil(self.escape_s)) + 1, dtype=float)
        straight = paths[:, at, None] + ahead[None, :, None] * velocity[:, None]
        return np.concatenate([apart, straight], axis=1)

    def _separation(self, path: np.ndarray, settled: list[np.ndarray]) -> float:
        """Smallest distance (km) between ``path`` and any settled path at the same instant,
        over every pair of their variants (each (V, T, 2): ``_separation_paths`` of the
        prediction and of its lossy-link variants)."""
        if not settled:
            return float(np.inf)
        gap = np.stack(settled)[:, :, None] - path[None, None]  # (S, V, V, T, 2)
        return float(np.hypot(gap[..., 0], gap[..., 1]).min())
