"""One decision step of the mission, stage by stage, each a unit a test can drive on its own:

1. **gather** (:meth:`DecisionStep.gather`): each UAV's planner inputs from what came back over
   MAVLink: position (its look of the decision instant, else its latest GLOBAL_POSITION_INT),
   cell, heading, sensor report, engagement outcome, active;
2. **plan** (:meth:`DecisionStep.plan`): the HAPF-ACO planner's step;
3. **envelope** (:meth:`DecisionStep.envelope`): the cell-level safety envelope
   (``safety_envelope.py``), then the flight-path layer (``flight_envelope.py``): the guided
   target and leg airspeed of every UAV;
4. **record** (:meth:`DecisionStep.record`): distance flown and the recorder's step (positions
   as measured);
5. **command batch** (:meth:`DecisionStep.command_batch`): engagement requests first, then
   guided targets (DO_REPOSITION) and leg airspeeds (DO_CHANGE_SPEED), as one batch;
6. **account** (:meth:`DecisionStep.account`): what the acknowledgements say: engagement
   outcomes, accepted targets and speeds, refusals.

Waiting for the decision instant is the pacing's (``pacing.py``); sending the batch is the
daemon's (acknowledged, retried, bounded by the step's deadline). The state the loop carries
from step to step is one :class:`LoopState` (what a checkpoint holds, ``checkpoint.LOOP_STATE``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from mavlink_bridge.mission.loop_state import LoopState, course_heading
from mavlink_bridge.results.mission_result import MissionAccount
from mavlink_bridge.safety.flight_envelope import FlightChoice, FlightEnvelope
from mavlink_bridge.safety.neighbour_flights import NeighbourFlights, neighbour_flights
from mavlink_bridge.safety.safety_envelope import SafetyEnvelope
from mavlink_bridge.vehicles.autopilot_adapter import autopilot_for
from mavlink_bridge.vehicles.flight_prediction import PlaneModel, fly_on, leg_speed_mps
from mavlink_bridge.vehicles.guided_commands import (
    Command,
    CommandRefusedError,
    change_speed_command,
    engagement_command,
)
from mavlink_bridge.vehicles.sensor_looks import look_report
from mavlink_bridge.vehicles.vehicle_state import Look, VehicleState
from mavlink_wire.protocol import (
    AUTOPILOT_COMPONENT_ID,
    CAMERA_COMPONENT_ID,
    command_name,
    result_name,
)
from planner.engagement import EngagementOutcome
from planner.geodesy import geodetic_to_local_km, local_km_to_geodetic
from planner.grid import Grid
from planner.scenario import Scenario
from planner.sensor_model import SensorReport


@dataclass
class StepInputs:
    """Each UAV's planner inputs at one decision instant."""

    step: int
    looks: dict[int, Look]
    active: np.ndarray  # (N,) bool
    reports: list[SensorReport | None]


@dataclass
class StepPlan:
    """The planner's decision and the cells it proposes (a finished UAV holds)."""

    decision: Any  # planner.planner_interface.StepDecision
    done: np.ndarray
    proposed_cells: np.ndarray
    proposed_headings: np.ndarray
    engagements_given: list[EngagementOutcome | None] = field(default_factory=list)


@dataclass
class CommandBatch:
    """One step's commands, engagement requests first (docs/daemon.md, "Engagements")."""

    requests: list[tuple[int, Command]]  # (UAV, engagement request)
    moves: list[tuple[int, tuple[float, float], Command]]  # (UAV, aim km rounded, reposition)
    speeds: list[Command]

    @property
    def commands(self) -> list[Command]:
        return [c for _, c in self.requests] + [c for *_, c in self.moves] + self.speeds


@dataclass
class DecisionStep:
    """The stages of one decision step over one swarm (see the module docstring)."""

    scenario: Scenario
    grid: Grid
    cell_envelope: SafetyEnvelope
    plane: PlaneModel
    flight_envelope: FlightEnvelope | None
    vehicles: list[VehicleState]  # index = UAV
    counters: MissionAccount
    lead_steps: float = 1.0
    leg_timing: bool = True
    max_refusals: int = 5
    #: lockstep: the planes hold at the decision instant; paced: they fly on while it is planned
    predict_from_now: bool = True
    #: paced: the vehicles' seconds per wall second (their speedup), to tell how old a plane's
    #: latest position report is on its own clock
    clock_rate: float = 1.0
    wall_clock: Callable[[], float] = time.monotonic
    send: Callable[[list[Command]], list[Command]] = lambda commands: commands
    say: Callable[[str], None] = lambda text: None
    target_values: dict[int, float] = field(default_factory=dict)
    #: airspeed last accepted by each vehicle (unknown at the start and after a restart)
    sent_speeds: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        if len(self.sent_speeds) != len(self.vehicles):
            self.sent_speeds = np.full(len(self.vehicles), np.nan)

    @property
    def n(self) -> int:
        return len(self.vehicles)

    def local_km(self, lat: float, lon: float) -> np.ndarray:
        x, y = geodetic_to_local_km(lat, lon, self.scenario.origin)
        return np.array([x[0], y[0]])

    # ------------------------------------------------------------------ 1. gather

    def gather(self, state: LoopState, step: int, looks: dict[int, Look]) -> StepInputs:
        """Each UAV's position, cell, heading and sensor report at this decision instant."""
        cfg = self.scenario.config
        n = self.n
        active = np.array([not v.lost for v in self.vehicles])
        reports: list[SensorReport | None] = [None] * n
        for i, v in enumerate(self.vehicles):
            if not active[i]:
                continue
            look = looks.get(i)
            look_km = None if look is None else self.local_km(look.lat_deg, look.lon_deg)
            # where the vehicle is now: its look, unless the link delayed that look past
            # position reports of a later step (then the look is an earlier decision
            # instant's, and a leg measured from it would span two steps)
            stale = (
                v.has_position
                and look is not None
                and look.time_boot_ms < (v.time_boot_ms - 500 * cfg.step_s)
            )
            if look is not None and look_km is not None and not stale:
                state.positions[i], state.positions_ms[i] = look_km, look.time_boot_ms
            elif v.has_position:
                self.counters.looks_missed += step > 0 and look is None
                state.positions[i] = self.local_km(v.lat_deg, v.lon_deg)
                state.positions_ms[i] = v.time_boot_ms
            cell = self.grid.cell_of(state.positions[i])
            if look is not None:  # where it looked, which is usually where it is
                reports[i] = look_report(
                    look, self.grid, self.scenario.origin, cfg.detection_radius_km,
                    cell=self.grid.cell_of(look_km),
                )  # fmt: skip
                state.observed[reports[i].cells[:, 0], reports[i].cells[:, 1]] = True
            # circling: around its take-off point (step 0) or held in its cell by the last step
            if step == 0 or np.array_equal(state.commanded_cells[i], state.cells[i]):
                state.headings[i] = self.leaving_heading(cell, course_heading(v), state.headings[i])
            elif np.array_equal(cell, state.commanded_cells[i]):
                state.headings[i] = state.commanded_headings[i]
            else:
                course = course_heading(v)
                state.headings[i] = state.commanded_headings[i] if course is None else course
            state.cells[i] = cell
        return StepInputs(step, looks, active, reports)

    def leaving_heading(self, cell: np.ndarray, course: int | None, came_in: int) -> int:
        """The heading a circling plane (around its take-off point, or held in its cell) leaves
        on: the course it flies now when a turn-limited path goes on from there
        (``SafetyEnvelope.viable``), else the viable heading nearest to it. Given the heading
        it came in on, a PX4 plane held in a corner heading out was held there for a whole
        mission (its 37 s circle nearly matched the 43 s step: the same outward course at every
        decision instant)."""
        now = came_in if course is None else course
        nearest_first = sorted(range(8), key=lambda h: min((h - now) % 8, (now - h) % 8))
        for heading in nearest_first:
            if self.cell_envelope.viable(cell, heading):
                return heading
        return now

    # ------------------------------------------------------------------ 2. plan

    def plan(self, state: LoopState, inputs: StepInputs) -> StepPlan:
        """The planner's step from the gathered inputs and the last step's engagement outcomes."""
        given = state.engagements
        decision = state.planner.step(
            state.cells.copy(), state.headings.copy(), inputs.reports, given,
            inputs.active.copy(), state.positions.copy(),
        )  # fmt: skip
        state.engagements = [None] * self.n
        done = np.asarray(decision.done, dtype=bool)
        proposed = np.where(done[:, None], self.home_cells(state), np.asarray(decision.next_cells))
        proposed_h = np.where(done, state.headings, np.asarray(decision.next_headings))
        return StepPlan(decision, done, proposed, proposed_h, list(given))

    # ------------------------------------------------------------------ 3. envelope

    def envelope(self, state: LoopState, inputs: StepInputs, plan: StepPlan) -> FlightChoice:
        """Cell-level envelope, then the flight-path layer: every UAV's guided target, the cell
        and heading it stands for, and its leg airspeed. Replacements are counted."""
        from_cells = np.where(plan.done[:, None], self.home_cells(state), state.cells)
        checked = self.cell_envelope.check(
            from_cells, state.headings, plan.proposed_cells, plan.proposed_headings,
            state.flown_km, state.home_km, inputs.active,
        )  # fmt: skip
        for o in checked.overrides:
            self.counters.overrides[o.reason] += 1
        flight = self.choose_flight(
            state, checked.next_cells, checked.next_headings, inputs.active, from_cells
        )
        for reason, count in flight.overrides.items():
            self.counters.overrides[reason] += count
        flight.replaced = [(o.uav, o.reason) for o in checked.overrides] + flight.replaced
        return flight

    def choose_flight(
        self,
        state: LoopState,
        next_cells: np.ndarray,
        next_headings: np.ndarray,
        active: np.ndarray,
        from_cells: np.ndarray | None = None,
    ) -> FlightChoice:
        """Guided targets whose predicted flight is safe (flight_envelope.py); without the
        flight-path envelope, the aim points of the checked cells. Paths are predicted from each
        plane's latest position, course and speed: in lockstep that is the decision instant
        (``positions``, measured at the vehicle's ``positions_ms``); in paced time the plane has
        flown on while the step was planned. ``from_cells``: the cell each move is judged from
        (a UAV the planner counts as home, ``done``, holds its home cell wherever its circle
        has taken it; default where each plane is)."""
        n, lead = self.n, self.lead_steps
        cells = state.cells if from_cells is None else from_cells
        positions, courses, speeds, elapsed_s = self.where_now(state, active)
        decision_positions = state.positions
        if self.flight_envelope is None:
            aims = np.array(
                [self.cell_envelope.aim_point_km(cells[i], next_cells[i], lead) for i in range(n)]
            )
            if self.leg_timing:
                speeds = leg_speed_mps(
                    self.plane,
                    positions,
                    self.grid.centre_km(cells),
                    self.grid.centre_km(next_cells),
                    speeds,
                    self.scenario.config.step_s,
                    np.arange(n),
                )
            else:
                speeds[:] = self.plane.speed_mps
            return FlightChoice(aims, next_cells, next_headings, speeds)
        previous = state.last_targets_km()
        return self.flight_envelope.choose(
            positions, courses, speeds, cells, state.headings, next_cells,
            next_headings, previous, state.flown_km, state.home_km, active, lead,
            decision_positions, elapsed_s, self.neighbours(state, positions, elapsed_s),
        )  # fmt: skip

    def neighbours(
        self, state: LoopState, positions_km: np.ndarray, elapsed_s: np.ndarray
    ) -> NeighbourFlights | None:
        """A planner node's neighbours' flights as it heard them (a planner with
        ``heard_flights``: ``onboard_planner.py``), advanced to now, those that may come near
        its plane (at ``positions_km`` now) before its next targets: its plane settles with
        them (``neighbour_flights.py``). None for the central daemon, which settles every pair
        of its planes itself."""
        heard = getattr(state.planner, "heard_flights", None)
        if heard is None or self.flight_envelope is None or self.n != 1:
            return None
        fe = self.flight_envelope
        return neighbour_flights(
            heard(), int(state.planner.uav), self.cell_envelope, fe.model,
            self.scenario.config.step_s, self.lead_steps, float(elapsed_s[0]), positions_km[0],
            fe.separation_reach_km,
        )  # fmt: skip

    def home_cells(self, state: LoopState) -> np.ndarray:
        """Each UAV's start cell. A UAV the planner counts as home (``done``: back next to its
        start, eq 37) is sent to circle it: sent to circle the cell it was in at each step
        instead, a plane at 100-150 m/s on a 1-2 km turn radius drifted a cell or more a step,
        and in the lockstep demo (paper-10uav seed 2) 1 of 10 ended within a cell of its start
        against 10 of 10 offline."""
        return self.grid.cell_of(state.home_km)

    def where_now(
        self, state: LoopState, active: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Each plane's position, course (rad from east) and speed now, and the seconds since
        the decision instant (when it was at ``state.positions``). In lockstep that is the
        decision instant. In paced time it is its latest position report, flown on along the
        way to the target it last accepted for as long as that report is old on its clock (the
        wall time since it came in x ``clock_rate``, at most two decision periods): at 30 %
        loss and 20x the latest report of a plane was 10 s old at a decision, and paths
        predicted from it as if it were now started a kilometre behind the plane."""
        n = self.n
        speeds = np.full(n, self.plane.speed_mps)
        courses = np.empty(n)
        positions = np.array(state.positions, dtype=float, copy=True)
        elapsed_s = np.zeros(n)
        stale_s = np.zeros(n)
        now = self.wall_clock()
        cap_s = 2.0 * self.scenario.config.step_s
        for i, v in enumerate(self.vehicles):
            if self.predict_from_now and v.has_position and active[i]:
                positions[i] = self.local_km(v.lat_deg, v.lon_deg)
                stale_s[i] = min(cap_s, max(0.0, (now - v.position_s) * self.clock_rate))
                elapsed_s[i] = max(0.0, (v.time_boot_ms - state.positions_ms[i]) / 1e3)
            if v.speed_mps > 1.0:
                courses[i], speeds[i] = v.course_rad, v.speed_mps  # over ground, from east
            else:
                courses[i] = int(state.headings[i]) * math.pi / 4
        flown = fly_on(self.plane, positions, courses, speeds, state.last_targets_km(), stale_s)
        return positions, courses, speeds, elapsed_s + flown

    # ------------------------------------------------------------------ 4. record

    def record(
        self, state: LoopState, inputs: StepInputs, plan: StepPlan, flight: FlightChoice
    ) -> None:
        """Distance flown (between measured cells, as the planner counts) and the recorder's
        step: the positions as measured, where the UAVs were sent next."""
        centres = self.grid.centre_km(state.cells)
        if inputs.step > 0:
            legs = np.hypot(*(centres - state.previous_centres).T)
            state.flown_km[inputs.active] += legs[inputs.active]
        state.previous_centres = centres
        state.recorder.record_step(
            state.positions.copy(),
            airborne=inputs.active.copy(),
            planned_km=self.grid.centre_km(flight.next_cells),
            done=plan.done,
        )

    # ------------------------------------------------------------------ 5. command batch

    def command_batch(
        self, state: LoopState, inputs: StepInputs, plan: StepPlan, flight: FlightChoice
    ) -> CommandBatch:
        """One batch: engagement requests first (each vehicle gets its request before its next
        guided target, so it is resolved where the planner asked for it), then the guided targets
        and the airspeed of each leg. An engagement left unanswered is asked again with the same
        sequence number (the camera replays its outcome, never engages twice) before any new
        one. A guided target already being flown is re-sent every 5 steps only."""
        active, step = inputs.active, inputs.step
        requests = [
            (i, engagement_command(v, state.pending_engage[i] or state.engage_seq[i] + 1))
            for i, v in enumerate(self.vehicles)
            if active[i]
            and (bool(plan.decision.engage[i]) or state.pending_engage[i])
            and i not in self.counters.cameraless
        ]
        for i, cmd in requests:
            state.engage_seq[i] = max(state.engage_seq[i], int(cmd.params[3]))
        aims = flight.aims_km
        lat, lon = local_km_to_geodetic(aims[:, 0], aims[:, 1], self.scenario.origin)
        moves = []
        for i, v in enumerate(self.vehicles):
            if not active[i]:
                continue
            aim = (round(float(aims[i, 0]), 3), round(float(aims[i, 1]), 3))
            if aim == state.last_target[i] and step % 5:
                continue  # already flying there (re-sent every 5 steps all the same)
            cmd = autopilot_for(v).reposition_command(
                v, float(lat[i]), float(lon[i]), self.scenario.altitude_m
            )
            moves.append((i, aim, cmd))
        return CommandBatch(requests, moves, self.speed_commands(flight.speeds_mps, active))

    def without_camera(self, uav: int, request: Command) -> bool:
        """Whether an unanswered engagement request shows that the vehicle has no camera: its
        autopilot answered the capture meant for component 100 itself (ArduPilot does, when no
        component 100 is on any of its links), or no camera was ever heard from it (no
        heartbeat, look or answer of component 100) through every try. Such a vehicle gets one
        warning and no more engagement requests (never a retry every step)."""
        v = self.vehicles[uav]
        own = v.acks.get((AUTOPILOT_COMPONENT_ID, request.command))
        if own is not None and own.serial > request.serial_before:
            why = (
                f"its autopilot answered {command_name(request.command)} for component "
                f"{CAMERA_COMPONENT_ID} with {result_name(own.result)}"
            )
        elif request.attempts >= 3 and not v.camera_heard():
            why = f"component {CAMERA_COMPONENT_ID} never heard"
        else:
            return False
        self.counters.cameraless.append(uav)
        self.say(
            f"warning: vehicle {v.key} has no camera ({why}): its engagements are off "
            f"for this mission; give it one with `swarmplan payload` (docs/sitl.md)"
        )
        return True

    def speed_commands(self, speeds_mps: np.ndarray, active: np.ndarray) -> list[Command]:
        """DO_CHANGE_SPEED for every active vehicle whose leg airspeed (rounded to 1 m/s)
        differs from the one it last accepted (leg timing only)."""
        if not self.leg_timing:
            return []
        wanted = np.round(speeds_mps)
        return [
            change_speed_command(v, float(wanted[i]))
            for i, v in enumerate(self.vehicles)
            if active[i] and wanted[i] != self.sent_speeds[i]
        ]

    # ------------------------------------------------------------------ 6. account

    def account_answers(
        self, state: LoopState, step: int, batch: CommandBatch, sent: list[Command]
    ) -> None:
        """What the acknowledgements of ``sent`` (the batch, in order) say."""
        n_req, n_moves = len(batch.requests), len(batch.moves)
        answered, moved = sent[:n_req], sent[n_req : n_req + n_moves]
        for (i, _), cmd in zip(batch.requests, answered, strict=True):
            state.pending_engage[i] = int(cmd.params[3]) if cmd.ack is None else 0
            if cmd.ack is None and self.without_camera(i, cmd):
                state.pending_engage[i] = 0
                continue
            if cmd.ack is None:
                continue  # unanswered: asked again at the next step
            target = int(cmd.ack.result_param2) if cmd.accepted else 0
            value = float(self.target_values.get(target, 0.0)) if target else 0.0
            state.engagements[i] = EngagementOutcome(target != 0, target, value)
            if target and target not in state.engaged_ids:
                state.engaged_ids.add(target)
                state.engaged_value += value
                state.recorder.record_engagement(step, i, target, value)
            elif not target:
                state.recorder.record_engagement_miss()
        self.speeds_answered(sent[n_req + n_moves :], step)
        for (i, aim, _), cmd in zip(batch.moves, moved, strict=True):
            if cmd.ack is not None and not cmd.accepted:
                state.refusals[i] += 1
                self.counters.refused_commands += 1
                self.say(f"warning: {cmd.describe_failure()} (step {step})")
                if state.refusals[i] >= self.max_refusals:
                    raise CommandRefusedError(
                        f"{cmd.describe_failure()} {state.refusals[i]} times in a row; check its "
                        f"mode, fence and STATUSTEXT messages"
                    )
            elif cmd.accepted:
                state.refusals[i] = 0
            if cmd.accepted:
                state.last_target[i] = aim

    def account(
        self,
        state: LoopState,
        step: int,
        batch: CommandBatch,
        sent: list[Command],
        flight: FlightChoice,
    ) -> None:
        """The answers, then what was commanded becomes what the next step compares with."""
        self.account_answers(state, step, batch, sent)
        state.commanded_cells = flight.next_cells.copy()
        state.commanded_headings = flight.next_headings.copy()

    def speeds_answered(self, commands: list[Command], step: int) -> None:
        """Note accepted airspeeds. A vehicle that refuses one (outside its AIRSPEED_MIN/MAX)
        ends leg timing for the run: every plane is asked back to the scenario's speed."""
        refused = [c for c in commands if c.ack is not None and not c.accepted]
        index = {id(v): i for i, v in enumerate(self.vehicles)}
        for cmd in commands:
            if cmd.accepted:
                self.sent_speeds[index[id(cmd.vehicle)]] = cmd.params[1]
        if not refused:
            return
        self.counters.refused_commands += len(refused)
        self.say(
            f"warning: {refused[0].describe_failure()} (step {step}, {refused[0].params[1]:g} "
            f"m/s); flying every leg at {self.plane.speed_mps:g} m/s from now on (set "
            f"--airspeed-range to the airframe's AIRSPEED_MIN:AIRSPEED_MAX, or --no-leg-timing)"
        )
        self.end_leg_timing()

    def end_leg_timing(self, vehicles: list[VehicleState] | None = None) -> list[Command]:
        """Back to the scenario's speed for ``vehicles`` (default: every vehicle still heard),
        best effort; no more leg timing in this run."""
        if not self.leg_timing:
            return []
        self.leg_timing = False
        if self.flight_envelope is not None:
            self.flight_envelope = replace(self.flight_envelope, leg_timing=False)
        cruise = self.plane.speed_mps
        if vehicles is None:
            vehicles = [v for v in self.vehicles if not v.lost]
        return self.send([change_speed_command(v, cruise) for v in vehicles])
