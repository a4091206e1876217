"""The decision loop of a mission: from the start (step 0) to its last step, each step waits for
its decision instant (``pacing.py``), runs its stages (``decision_step.py``: gather, plan,
envelope, record, command batch, send, account), guides the planes flying home during the
mission (``way_home/flight_home.py``), tells the listeners and writes the checkpoint.

:class:`DecisionLoop` owns the loop's state (:class:`~mavlink_bridge.mission.loop_state.LoopState`,
the stages, the pacing, the hold when late) and takes the mission context
(``context.MissionContext``), the flight home, the track audit and the loss watch's pump.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from mavlink_bridge.mission.context import MissionContext
from mavlink_bridge.mission.decision_step import DecisionStep
from mavlink_bridge.mission.flown_planning import flight_margin_km, planning_scenario
from mavlink_bridge.mission.keeping_up import HoldWhenLate, held_apart
from mavlink_bridge.mission.loop_state import LoopState, course_heading
from mavlink_bridge.mission.operator_actions import OperatorActions
from mavlink_bridge.mission.pacing import (
    STEP_DEADLINE_SHARE,
    DecisionInstant,
    Lateness,
    PacingChoice,
    PacingContext,
)
from mavlink_bridge.mission.resume_takeback import (
    CONTINUE,
    LAUNCH,
    TakeBack,
    account_outage,
    outage_s,
)
from mavlink_bridge.results.checkpoint import Checkpoint, CheckpointWriter
from mavlink_bridge.results.checkpoint_resume import resume_loop_state
from mavlink_bridge.results.mission_result import LookTimes, StepRecord, StepStatus
from mavlink_bridge.safety.track_audit import TrackAudit
from mavlink_bridge.way_home.flight_home import FlightHomePhase
from planner.grid import heading_of_angle
from planner.metrics import turned_home_warning
from planner.pursuit_log import PursuitLog
from planner.scenario import Scenario, UavStart


class DecisionLoop:
    """The decision steps of one mission (see the module docstring)."""

    def __init__(
        self,
        ctx: MissionContext,
        home: FlightHomePhase,
        audit: TrackAudit,
        watch: Callable[[int], None],
        operator: OperatorActions | None = None,
    ) -> None:
        self.ctx = ctx
        self.home = home
        self.audit = audit
        self.watch = watch  # loss and return, at every pump of the loop (``vehicle_loss.py``)
        #: the operator's actions from the mission view, at the top of each step
        self.operator = operator
        cfg = ctx.scenario.config
        self.state: LoopState | None = None  # once it runs
        self.stages: DecisionStep | None = None
        self.pacing: PacingChoice | None = None
        #: each step's look time stamps, to join a simulator's truth (the per-target account)
        self.look_times = LookTimes()
        #: held planes no point keeps d_min apart (said once: ``hold_apart``)
        self.stuck_in_hold: set[int] = set()
        #: paced time: hold the planes at their last safe targets while late (keeping_up.py)
        self.hold_policy = (
            None
            if ctx.options.lockstep
            else HoldWhenLate(
                cfg.step_s if ctx.options.late_bound_s is None else ctx.options.late_bound_s,
                ctx.say,
            )
        )
        self.ended_early: str | None = None  # why the mission ended before its last step
        self._target_values = {t.id: float(t.value) for t in ctx.scenario.targets}

    # ------------------------------------------------------------------ the start

    def starts_from_telemetry(self) -> tuple[UavStart, ...]:
        """Each UAV's start: the cell centre of its home (launch) position, heading from its
        course (nearest of the eight); a vehicle without position falls back to the scenario's."""
        ctx = self.ctx
        fallback = ctx.scenario.starts_for_seed(ctx.options.seed)
        starts = []
        for i, u in enumerate(ctx.fleet):
            v = ctx.vehicle(i)
            if not v.has_position and v.home is None:
                starts.append(fallback[u] if u < len(fallback) else UavStart(0.5, 0.5, 0.0))
                continue
            lat, lon = (v.home[0], v.home[1]) if v.home is not None else (v.lat_deg, v.lon_deg)
            cell = ctx.grid.cell_of(ctx.local_km(lat, lon))
            centre = ctx.grid.centre_km(cell)
            heading = course_heading(v)
            if heading is None:
                heading = (
                    int(heading_of_angle(math.radians(fallback[u].heading_deg)))
                    if u < len(fallback)
                    else 0
                )
            starts.append(UavStart(float(centre[0]), float(centre[1]), heading * 45.0))
        return tuple(starts)

    def flight_margin_km(self) -> float:
        """The threat clearance the planner plans every move and the way home with
        (``flown_planning.flight_margin_km``): the flight envelope's for a guided target, its
        loiter circle as flown at cruise plus the predicted margin (2.39 km for the simulator's
        100 m/s plane, 0.41 km for ArduPlane's defaults), at least the cell-level margin.
        Planned at the paper's 0 km, the planner's way home hugged a threat that close and the
        envelope replaced its moves one by one: the plane came home late (paper-10uav demo: 8.2
        of 10 home over seeds 1-6 against 9.9 offline; docs/parameters.md)."""
        fe = self.ctx.flight_envelope
        return flight_margin_km(
            self.ctx.envelope.threat_margin_km,
            None if fe is None else fe.model,
            0.0 if fe is None else fe.threat_margin_km,
        )

    def planning_scenario(self) -> Scenario:
        """The scenario as this daemon's planner plans it, for the airframes flown: the margins a
        flown plane needs (``flown_planning.planning_scenario``): separation on top of d_min,
        the flight envelope's threat clearance, a few steps more kept back for the way home."""
        ctx = self.ctx
        return planning_scenario(
            ctx.scenario,
            ctx.steps,
            ctx.envelope.separation_margin_km,
            ctx.options.home_reserve_extra_steps,
            self.flight_margin_km(),
        )

    def start_state(
        self,
        planner_cls: Any,
        recorder_cls: Any,
        starts: tuple[UavStart, ...] | None = None,
        consumed: list[int] | None = None,
    ) -> LoopState:
        """The loop's state at step 0: the planner and recorder from the UAVs' launch points
        (``starts``, else from telemetry). Real planes stray from cell centres (turn circle
        ~1 km, 14 s diagonal legs), so the planner plans with the margins a flown plane needs
        (``flown_planning.planning_scenario``); the recorder keeps judging against the
        scenario's own limits."""
        ctx = self.ctx
        starts = self.starts_from_telemetry() if starts is None else starts
        planner = planner_cls(self.planning_scenario(), starts, ctx.options.seed)
        PursuitLog().attach(planner)  # the planner's half of the per-target account (read-only)
        recorder = recorder_cls(
            ctx.scenario,
            starts,
            turn_tolerance_deg=ctx.options.turn_tolerance_deg,
            home_reach_km=float(ctx.plane.loiter_reach_km(ctx.plane.speed_mps)),
        )
        if consumed is None:
            consumed = [v.latest_look for v in ctx.vehicles()]
        return LoopState.start(ctx.grid, planner, recorder, starts, consumed)

    def make_stages(self) -> DecisionStep:
        """The decision step's stages over the expected vehicles."""
        ctx = self.ctx
        return DecisionStep(
            scenario=ctx.scenario,
            grid=ctx.grid,
            cell_envelope=ctx.envelope,
            plane=ctx.plane,
            flight_envelope=ctx.flight_envelope,
            vehicles=ctx.vehicles(),
            counters=ctx.account,
            lead_steps=ctx.options.lead_steps,
            leg_timing=ctx.options.leg_timing,
            max_refusals=ctx.options.max_refusals,
            predict_from_now=ctx.clock is None,
            clock_rate=ctx.time_scale,
            send=ctx.send,
            say=ctx.say,
            target_values=self._target_values,
        )

    def make_pacing(self) -> PacingChoice:
        ctx = self.ctx
        pacing = PacingContext(
            link=ctx.require_link(),
            vehicles=ctx.vehicles,
            watch=self.watch,
            step_s=ctx.scenario.config.step_s,
            time_scale=ctx.options.time_scale,
            lost_after_s=ctx.options.lost_after_s,
            account=ctx.account,
            say=ctx.say,
        )
        return PacingChoice(pacing, ctx.clock)

    def first_instant(self) -> DecisionInstant:
        """Step 0 is the start (no wait): its commands are due within the paced deadline."""
        if self.ctx.clock is not None:
            return DecisionInstant(0, {}, None, "lockstep")
        period_s = self.ctx.scenario.config.step_s / max(self.ctx.options.time_scale, 1e-6)
        return DecisionInstant(0, {}, time.monotonic() + STEP_DEADLINE_SHARE * period_s, "start")

    def resume(self, resume_from: Checkpoint, take_back: list[TakeBack], planner: Any) -> bool:
        """A restarted daemon: the state after the checkpoint's step, with the outage each plane
        that continues flew added to its range account. False: no plane can continue."""
        ctx = self.ctx
        ctx.say(
            f"resuming from the checkpoint of step {resume_from.step} "
            f"({ctx.options.checkpoint_path})"
        )
        state = self.state = LoopState.from_checkpoint(
            resume_loop_state(ctx.account, resume_from, planner)
        )
        account_outage(state, take_back, ctx.index_of)
        if take_back and not any(t.decision in (CONTINUE, LAUNCH) for t in take_back):
            self.ended_early = "completed at the resume: no plane can continue (all sent home)"
            ctx.say(f"mission {self.ended_early}")
            return False
        return True

    def rejoin(self, planner: Any, first_step: int) -> int:
        """A resumed planner node (one that has ``rejoin``): the step the swarm is at, heard
        from its neighbours within a decision period and a half, else the step of the
        mission's clock, the outage counted in decision periods (``OnboardPlanner.rejoin``).
        The daemon carries on from ``first_step``."""
        rejoin = getattr(planner, "rejoin", None)
        ctx = self.ctx
        if rejoin is None or ctx.options.checkpoint_path is None:
            return first_step
        path, step_s = ctx.options.checkpoint_path, ctx.scenario.config.step_s

        def clock_step() -> int:  # (the checkpoint's step: first_step - 1)
            return first_step - 1 + max(1, int(outage_s(path, ctx.time_scale) // step_s))

        step, how = rejoin(first_step, clock_step, ctx.steps, 1.5 * step_s / ctx.time_scale)
        ctx.say(f"rejoined the swarm at step {step} ({how}; {step - first_step} steps missed)")
        return step

    # ------------------------------------------------------------------ the steps

    def run(
        self,
        planner_cls: Any,
        recorder_cls: Any,
        resume_from: Checkpoint | None = None,
        take_back: list[TakeBack] | None = None,
        checkpoints: CheckpointWriter | None = None,
        elapsed_s: Callable[[], float] = lambda: 0.0,
    ) -> None:
        """The decision steps, from the start (step 0), or the step after ``resume_from``'s,
        to ``steps``: wait for the decision instant, gather, plan, envelope, record, command
        batch, send, account, tell listeners, checkpoint (with ``elapsed_s()`` of the run)."""
        ctx = self.ctx
        link = ctx.require_link()
        with link.keepalive():  # (the planner's beliefs of hundreds of UAVs: many seconds)
            state = self.state = self.start_state(planner_cls, recorder_cls)
        stages = self.stages = self.make_stages()
        pacing = self.pacing = self.make_pacing()
        first_step = 0
        if resume_from is not None:
            if not self.resume(resume_from, take_back or [], state.planner):
                return
            state, first_step = self.state, resume_from.step + 1
            first_step = self.rejoin(state.planner, first_step)
        for step in range(first_step, ctx.steps + 1):  # the start, then one record per step
            instant = pacing.wait(step, state.consumed) if step > 0 else self.first_instant()
            if self.operator_ends(step, state):
                break
            with link.keepalive():  # the step's computing: our heartbeat goes on meanwhile
                inputs = stages.gather(state, step, instant.looks)
                plan = stages.plan(state, inputs)
                flight = stages.envelope(state, inputs, plan)
                stages.record(state, inputs, plan, flight)
                if step < ctx.steps:  # the mission's steps' decisions, as offline counts them
                    state.recorder.record_modes(plan.decision.modes)
                    if step == 0 and state.recorder.turned_home_at_start:
                        ctx.say(f"warning: {turned_home_warning(ctx.steps)}")
                batch = stages.command_batch(state, inputs, plan, flight)
            # how late the step's commands go out, measured once (pacing.Lateness)
            lateness = pacing.current.lateness(instant) if step > 0 else None
            held = self.holds(step, lateness)
            if held:
                self.audit.set_phase("hold")  # nothing new: the planes circle their last targets
                self.hold_apart(state, inputs.active, instant.deadline)
            else:
                self.audit.set_phase("mission")
                sent = ctx.send(batch.commands, deadline=instant.deadline)
                stages.account(state, step, batch, sent, flight)
            # planes their fence (or a failsafe) switched to RTL through a zone: guided out;
            # planes a resumed daemon sent home: on their safe way home
            homeward = self.home.guide_stray_returns() + self.home.guide_sent_home()
            ctx.send(homeward, deadline=instant.deadline)
            self.look_times.note(step, state.positions_ms, inputs.active)
            late = lateness is not None and lateness.late
            self.tell_listeners(state, inputs, plan, flight, late, held)
            if checkpoints is not None:  # atomically, after every step
                checkpoints.save(step, ctx.account, state.checkpoint_view(), elapsed_s())
            if plan.done.all() and not ctx.scenario.config.home_by_end:
                break  # (home_by_end: the mission ends at its last step, as offline)
        ctx.options = replace(ctx.options, leg_timing=stages.leg_timing)

    def operator_ends(self, step: int, state: LoopState) -> bool:
        """The operator's actions queued since the last step (``operator_actions.py``); True
        when they end the mission before this step (``ended_early`` says how)."""
        if self.operator is None:
            return False
        if self.operator.apply(step, state.planner):
            self.watch(step)  # a plane the operator sent home is lost to the planner from now
        if self.operator.ended is None:
            return False
        self.ended_early = self.operator.ended
        self.ctx.say(f"mission {self.ended_early}")
        return True

    def holds(self, step: int, lateness: Lateness | None) -> bool:
        """Is this step held: the operator holds the search (``operator_actions.py``), or, in
        paced time, it is too late to fly (``keeping_up.HoldWhenLate``)?"""
        if self.operator is not None and self.operator.holding:
            self.operator.held_steps += 1
            return True
        if self.hold_policy is None or lateness is None:
            return False
        return self.hold_policy.hold(step, lateness.seconds)

    def hold_apart(self, state: LoopState, active: np.ndarray, deadline: float | None) -> None:
        """Held planes whose circles at their last targets would come within d_min of each
        other: one of each pair is moved apart (``keeping_up.held_apart``), and the point it
        accepts becomes its last target. Says who moves, and who no point keeps apart."""
        ctx, stages = self.ctx, self.stages
        assert stages is not None
        positions, courses, _speeds, _elapsed = stages.where_now(state, active)
        planes, index = [], {}
        for i, v in enumerate(ctx.vehicles()):
            target = state.last_target[i]
            if active[i] and target is not None and v.has_position and not v.lost:
                planes.append((v.key, positions[i], float(courses[i]), np.array(target)))
                index[v.key] = i
        if len(planes) < 2:
            return
        moves, stuck = held_apart(self.home.return_separation(), planes)
        commands = [
            self.home.reposition_to(ctx.vehicle(index[sid]), xy) for sid, xy in moves.items()
        ]
        for c in ctx.send(commands, deadline=deadline) if commands else []:
            sid = c.vehicle.key
            if c.accepted:
                state.last_target[index[sid]] = (float(moves[sid][0]), float(moves[sid][1]))
                ctx.say(
                    f"vehicle {sid} holds at ({moves[sid][0]:.1f}, {moves[sid][1]:.1f}) km: "
                    "circling its last target it would come within d_min of another held plane"
                )
        for sid in set(stuck) - self.stuck_in_hold:
            ctx.say(
                f"warning: held vehicle {sid} circles within d_min of another held plane and "
                "no point nearby keeps it apart"
            )
        self.stuck_in_hold = set(stuck)

    def tell_listeners(
        self, state: LoopState, inputs: Any, plan: Any, flight: Any, late: bool, held: bool = False
    ) -> None:
        """The progress callback (StepStatus) and the step listeners (StepRecord; a held step's
        aims are the targets the planes circle, not the ones planned and not sent)."""
        ctx, active = self.ctx, inputs.active
        status = StepStatus(
            inputs.step,
            ctx.steps,
            int(active.sum()),
            [i + 1 for i in range(ctx.n) if not active[i]],
            float(state.observed.mean()),
            len(state.engaged_ids),
            state.engaged_value,
            sum(ctx.account.overrides.values()),
        )
        if ctx.options.on_step is not None:
            ctx.options.on_step(status)
        if not ctx.options.step_listeners:
            return
        record = StepRecord(
            status=status,
            positions_km=state.positions.copy(),
            positions_ms=state.positions_ms.copy(),
            cells=state.cells.copy(),
            headings=state.headings.copy(),
            next_cells=np.array(flight.next_cells, copy=True),
            aims_km=held_aims(flight.aims_km, state) if held else np.array(flight.aims_km),
            speeds_mps=np.array(flight.speeds_mps, copy=True),
            active=active.copy(),
            done=plan.done.copy(),
            engage=np.asarray(plan.decision.engage, dtype=bool).copy(),
            late=late,
            planner=state.planner,
            engagements=tuple(
                (e["uav"], e["target_id"], e["value"])
                for e in state.recorder.engagements
                if e["step"] == inputs.step
            ),
            modes=np.asarray(plan.decision.modes).copy(),
            overrides=tuple(flight.replaced),
        )
        for listener in ctx.options.step_listeners:
            listener(record)


def held_aims(planned_km: np.ndarray, state: LoopState) -> np.ndarray:
    """A held step's aims: the target each plane last accepted, where it has one."""
    last = state.last_targets_km()
    return np.where(np.isfinite(last), last, planned_km)
