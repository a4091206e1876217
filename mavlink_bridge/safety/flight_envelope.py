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
  until late: ``lossy_link_paths.py``), every variant of a plane against every variant of the
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
closest to (``flight_settling.py``). Replacements of the planner's cell are counted as
``predicted_threat`` / ``predicted_separation`` overrides.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from mavlink_bridge.safety.flight_candidates import (
    Candidate,
    CandidateRows,
    candidate_rows,
    plane_candidates,
)
from mavlink_bridge.safety.flight_settling import Settling
from mavlink_bridge.safety.lossy_link_paths import LossyLinkPaths, lossy_link_paths
from mavlink_bridge.safety.neighbour_flights import (
    NeighbourFlights,
    joined_inputs,
    model_with_neighbours,
)
from mavlink_bridge.safety.safety_envelope import SafetyEnvelope
from mavlink_bridge.vehicles.flight_prediction import PlaneModel, predict_paths
from planner.constraints import segment_clearance
from planner.grid import heading_of_angle


@dataclass
class FlightChoice:
    """The guided target and airspeed of every UAV and the cell/heading it stands for."""

    aims_km: np.ndarray  # (N, 2)
    next_cells: np.ndarray  # (N, 2)
    next_headings: np.ndarray  # (N,)
    speeds_mps: np.ndarray  # (N,) airspeed to fly the leg at
    overrides: dict[str, int] = field(default_factory=dict)
    #: (UAV, reason) of each replacement counted in ``overrides`` (and, after the cell
    #: envelope, of its overrides too): the mission view's timeline names the UAV
    replaced: list[tuple[int, str]] = field(default_factory=list)
    min_separation_km: float = np.inf  # predicted, between the accepted paths
    #: the same over every lossy-link variant of each (paced time; as predicted in lockstep)
    min_separation_lossy_km: float = np.inf


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
        return float(np.pi / 2 / self.model.turn_rate_radps(self.model.fastest_leg_mps))

    @property
    def separation_reach_km(self) -> float:
        """How far apart (km) two planes may be now and still come within the separation kept
        (``min_separation_km + separation_margin_km``) over the instants it is kept at: both
        flying at each other at the fastest leg airspeed for ``separation_horizon_steps`` and
        ``escape_s``."""
        kept_s = max(1.0, self.separation_horizon_steps) * self.step_s + self.escape_s
        need = self.cells.min_separation_km + self.separation_margin_km
        return 2.0 * self.model.fastest_leg_mps * kept_s / 1000.0 + need

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
        neighbours: NeighbourFlights | None = None,
    ) -> FlightChoice:
        """Guided targets for every UAV at ``positions_km`` flying at ``speeds_mps`` now
        (inactive ones keep the proposal; nothing is sent). In paced time a plane is
        ``elapsed_s`` past the decision instant, when it was at ``decision_positions_km`` (where
        the measured chord to the next decision instant starts); by default it is there now.
        ``neighbours``: planes this envelope does not command (a planner node's neighbours,
        ``neighbour_flights.py``), predicted as these are: those whose claim was heard settle
        with these UAVs in the scenario's UAV order, on the candidates their own envelopes
        have, so that each node takes the choice the central settling would give its plane;
        the others' flights are given, settled first: every UAV is kept apart from them."""
        n = len(cells)
        if decision_positions_km is None:
            decision_positions_km = positions_km
        elapsed = np.zeros(n) if elapsed_s is None else np.asarray(elapsed_s, dtype=float)
        if neighbours is not None and len(neighbours):
            joined = replace(self, model=model_with_neighbours(self.model, n, len(neighbours)))
            own = (positions_km, courses_rad, speeds_mps, cells, headings, proposed_cells,
                   proposed_headings, previous_aims_km, flown_km, home_km, active)  # fmt: skip
            return joined._choose(
                *joined_inputs(own, neighbours, home_km), lead,
                np.concatenate([decision_positions_km, neighbours.positions_km]),
                np.concatenate([elapsed, np.zeros(len(neighbours))]), n, neighbours,
            )  # fmt: skip
        return self._choose(
            positions_km, courses_rad, speeds_mps, cells, headings, proposed_cells,
            proposed_headings, previous_aims_km, flown_km, home_km, active, lead,
            decision_positions_km, elapsed, n, None,
        )  # fmt: skip

    def _choose(
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
        decision_positions_km: np.ndarray,
        elapsed: np.ndarray,
        own: int,
        neighbours: NeighbourFlights | None,
    ) -> FlightChoice:
        """``choose`` over the first ``own`` UAVs, the rest being ``neighbours`` (given)."""
        table = self._candidate_rows(
            positions_km, speeds_mps, cells, headings, proposed_cells, proposed_headings,
            previous_aims_km, flown_km, home_km, active, lead, own, neighbours,
        )  # fmt: skip
        paths = predict_paths(
            self.model.rows(np.array([i for i, _ in table.rows], dtype=int)),
            table.starts_km,
            np.array([courses_rad[i] for i, _ in table.rows]),
            table.aims_km,
            self.horizon_s,
            speed_mps=table.speeds_now_mps,
            commanded_mps=table.commanded_mps,
        )
        lossy = self._lossy_paths(table, positions_km, courses_rad, speeds_mps, previous_aims_km)
        kept_apart = self._kept_apart(paths, lossy)
        clearance = self._clearance(table, paths, lossy, decision_positions_km, elapsed)
        settling = Settling(
            [len(c) for c in table.candidates],
            table.row_of,
            clearance,
            self.threat_margin_km,
            self.cells.min_separation_km + self.separation_margin_km,
            fixed=frozenset(own + np.flatnonzero(~neighbours.free)) if neighbours else frozenset(),
            order=None if neighbours is None else neighbours.settling_order(own),
        )
        # kept apart as a lossy link may fly them where some candidate can be; where none can
        # (two planes whose last legs already close within the delay), as predicted
        nominal = kept_apart[:, :1]
        tiers = [kept_apart, nominal] if kept_apart.shape[1] > 1 else [nominal]
        chosen = settling.settle(tiers)
        mine = {i: k for i, k in chosen.items() if i < own}
        choice = self._choice(
            table, paths, mine, settling, headings[:own], proposed_cells[:own],
            proposed_headings[:own],
        )  # fmt: skip
        choice.min_separation_km = settling.closest_km(nominal, chosen)
        choice.min_separation_lossy_km = (
            settling.closest_km(kept_apart, chosen) if len(tiers) > 1 else choice.min_separation_km
        )
        return choice

    # ------------------------------------------------------------------ pieces

    def _candidate_rows(
        self,
        positions_km: np.ndarray,
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
        own: int,
        neighbours: NeighbourFlights | None,
    ) -> CandidateRows:
        """Every active UAV's candidates (``flight_candidates.py``; none for an inactive one),
        as the rows of one batch; each neighbour's one given flight after them."""
        candidates = [
            plane_candidates(
                self.cells,
                self.leg_timing,
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
            for i in range(own)
        ]
        for m in range(0 if neighbours is None else len(neighbours)):
            j = own + m
            if neighbours.free[m]:  # its own envelope's candidates, as this one would judge them
                candidates.append(plane_candidates(
                    self.cells, self.leg_timing, cells[j], int(headings[j]), proposed_cells[j],
                    int(proposed_headings[j]), previous_aims_km[j], 0.0, home_km[j], lead,
                ))  # fmt: skip
            else:  # its one flight, as given
                candidates.append([Candidate(proposed_cells[j], int(proposed_headings[j]),
                                             neighbours.aims_km[m], derived=True)])  # fmt: skip
        return candidate_rows(
            candidates, self.cells.grid, self.model, self.step_s, self.leg_timing, cells,
            positions_km, speeds_mps,
        )  # fmt: skip

    def _lossy_paths(
        self,
        table: CandidateRows,
        positions_km: np.ndarray,
        courses_rad: np.ndarray,
        speeds_mps: np.ndarray,
        previous_aims_km: np.ndarray,
    ) -> LossyLinkPaths | None:
        """The candidates' lossy-link variants (``lossy_link_paths``), judged for threats (when
        there are any) and, paced, for separation: not predicted when neither needs it
        (lockstep among no threats)."""
        paced = round(self.command_delay_s) >= 1  # as ``lossy_link_paths`` counts it
        threats = len(self.cells.threat_radius_km) > 0
        if not (table.rows and (threats or paced)):
            return None
        return lossy_link_paths(
            self.model,
            self.horizon_s,
            self.command_delay_s,
            positions_km,
            courses_rad,
            speeds_mps,
            previous_aims_km,
            table.uav,
            table.aims_km,
            table.commanded_mps,
        )

    def _kept_apart(self, paths: np.ndarray, lossy: LossyLinkPaths | None) -> np.ndarray:
        """(M, V, T, 2): the instants each candidate is kept apart at, as predicted and, in
        paced time, as each lossy-link variant flies it (a late or lost command)."""
        kept_apart = self._separation_paths(paths)[:, None]
        if lossy is not None and lossy.from_now is not None:
            variants = [self._separation_paths(v) for v in lossy.from_now]
            kept_apart = np.stack([kept_apart[:, 0], *variants], axis=1)
        return kept_apart

    def _clearance(
        self,
        table: CandidateRows,
        paths: np.ndarray,
        lossy: LossyLinkPaths | None,
        decision_positions_km: np.ndarray,
        elapsed: np.ndarray,
    ) -> np.ndarray:
        """(M,) each candidate's smallest distance (km) to a threat edge: along its predicted
        path and the chords between decision instants, around its loiter circle, along every
        lossy-link variant (when there are threats), and around the circle a failsafe would
        fly anywhere on its way (``failsafe_circle``)."""
        row_uav = table.uav
        fastest = np.maximum(table.speeds_now_mps, table.commanded_mps)
        clearance = np.minimum(
            self._threat_clearance(
                paths,
                np.asarray(decision_positions_km, dtype=float)[row_uav].reshape(-1, 2),
                elapsed[row_uav],
            ),
            self._loiter_clearance(table.aims_km, fastest),
        )
        if lossy is not None and len(self.cells.threat_radius_km) > 0:
            flown = lossy.from_command.reshape(-1, *lossy.from_command.shape[2:])
            clearance = np.minimum(
                clearance,
                self._polyline_clearance(flown).reshape(len(lossy.from_command), -1).min(axis=0),
            )
        if self.failsafe_circle:
            clearance = np.minimum(clearance, self._failsafe_circle_clearance(paths, fastest))
        return clearance

    def _choice(
        self,
        table: CandidateRows,
        paths: np.ndarray,
        chosen: dict[int, int],
        settling: Settling,
        headings: np.ndarray,
        proposed_cells: np.ndarray,
        proposed_headings: np.ndarray,
    ) -> FlightChoice:
        """The chosen candidates as guided targets (inactive UAVs: the planner's cell at
        cruise), counting each replacement of the planner's cell as a ``predicted_threat``
        override (its cell broke the threat rule) or a ``predicted_separation`` one. Flying the
        planner's cell slower is not a replacement."""
        grid = self.cells.grid
        n = len(proposed_cells)
        row_of, threat_ok = settling.row_of, settling.threat_ok
        out = FlightChoice(
            grid.centre_km(proposed_cells),
            np.array(proposed_cells, dtype=np.int64, copy=True),
            np.array(proposed_headings, dtype=np.int64, copy=True),
            np.full(n, self.model.speed_mps),
            {"predicted_threat": 0, "predicted_separation": 0},
        )
        for i, k in chosen.items():
            r = row_of[(i, k)]
            cand = table.candidates[i][k]
            kept = k == 1 and cand.cruise  # the planner's cell, only flown slower
            if k != 0 and not kept:
                first = row_of[(i, 0)]
                broken = "predicted_separation" if threat_ok[first] else "predicted_threat"
                out.overrides[broken] += 1
                out.replaced.append((int(i), broken))
            out.aims_km[i] = cand.aim
            out.speeds_mps[i] = table.commanded_mps[r]
            if cand.derived:
                out.next_cells[i], out.next_headings[i] = self._flown_cell(paths[r], headings[i])
            else:
                out.next_cells[i], out.next_headings[i] = cand.cell, cand.heading
        return out

    def _flown_cell(self, path: np.ndarray, heading: int) -> tuple[np.ndarray, int]:
        """The cell and heading a kept-going or circling plane stands for: where its predicted
        path is one decision step on, heading the way it moves there (``heading`` if it does
        not move)."""
        grid = self.cells.grid
        last = len(path) - 1  # samples are one second apart
        per_step = min(max(1, round(self.step_s)), last)
        end, before = path[per_step], path[per_step - 1]
        move = end - before
        return grid.cell_of(end), (
            int(heading_of_angle(np.arctan2(move[1], move[0]))) if np.any(move) else int(heading)
        )

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
