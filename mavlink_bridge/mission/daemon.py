"""The planner daemon: flies a swarm of MAVLink vehicles with the HAPF-ACO planner.

One mission, in order:

1. the launch (``launch.py``): discover every expected system id, wait until each
   autopilot is ready, upload the threat zones as fence exclusion circles, arm, take off, GUIDED,
   ask for the homes;
2. the decision loop (``decision_loop.py``): every step waits for its decision instant
   (``pacing.py``), then runs its stages (``decision_step.py``): gather each UAV's inputs, plan,
   flight envelope, record, command batch, send (acknowledged, retried), account; step
   listeners get a read-only :class:`~mavlink_bridge.results.mission_result.StepRecord`;
3. the one exit path, also on an error, Ctrl-C or SIGTERM (:meth:`MissionDaemon.finish`): RTL to
   every airborne vehicle still reachable and the watch of the flight home
   (``way_home/flight_home.py``), the result of what was flown.

Each phase owns its state and takes the mission's context (``context.MissionContext``: the
link, the vehicles, the clock, the airframe in force, the counters, ``send`` and ``say``);
:class:`MissionDaemon` builds them, runs them in order and keeps what the result needs.

A vehicle whose link went away, silent for ``lost_after_s``, or (in the loop) disarmed or out of
GUIDED is lost (inactive to the planner; the others go on) and rejoins when it is back
(``vehicle_loss.py``). What is recorded comes from what came back over MAVLink: positions from
the looks / telemetry, engagements from their acknowledged outcomes (``mission_result.py``).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from typing import Any

from mavlink_bridge.mission.context import MIN_RETRY_S, STEP_SENDS, MissionContext
from mavlink_bridge.mission.decision_loop import DecisionLoop
from mavlink_bridge.mission.keeping_up import measure_step_wall_s, refuse_unkeepable_time_scale
from mavlink_bridge.mission.launch import Launch, LaunchPhase, launch_phases, run_launch
from mavlink_bridge.mission.lockstep_clock import LockstepClock
from mavlink_bridge.mission.operator_actions import OperatorActions
from mavlink_bridge.mission.options import DaemonOptions
from mavlink_bridge.mission.resume_takeback import TakeBack
from mavlink_bridge.results.checkpoint import (
    DAEMON_STATE,
    Checkpoint,
    CheckpointError,
    CheckpointWriter,
    load_for_mission,
    mission_fingerprint,
)
from mavlink_bridge.results.mission_result import (
    ALGORITHM,
    MissionReport,
    StepRecord,
    StepStatus,
    mavlink_extra,
)
from mavlink_bridge.safety.track_audit import TrackAudit, position_listener
from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_bridge.vehicles.telemetry_plausibility import PlausibilityFilter, PlausibilityLimits
from mavlink_bridge.vehicles.vehicle_loss import GONE, LossWatch, SwarmPauses
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_bridge.way_home.flight_home import FlightHomePhase
from mavlink_bridge.way_home.home_watch import watch_flight_home
from mavlink_wire.protocol import mavlink
from mavlink_wire.tlog import TlogWriter
from planner.errors import UserError
from planner.geodesy import geodetic_to_local_km
from planner.pursuit_log import PursuitLog
from planner.scenario import Scenario, UavStart


class MissionInterrupted(KeyboardInterrupt):
    """A signal ends the mission (raised by the command line's SIGTERM handler)."""

    def __init__(self, signal_name: str) -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name


def ended_by(exc: BaseException) -> str:
    """How an exception ended the mission, for the result (``ended``)."""
    if isinstance(exc, MissionInterrupted):
        return f"interrupted ({exc.signal_name})"
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted (Ctrl-C)"
    if isinstance(exc, UserError):
        return f"error: {exc}"
    return f"error: {type(exc).__name__}: {exc}"


def _import_planner() -> tuple[Any, Any]:
    from planner.hapf_aco import HapfAcoPlanner
    from planner.metrics import MissionRecorder

    return HapfAcoPlanner, MissionRecorder


class MissionDaemon:
    """Runs one mission over MAVLink (see the module docstring)."""

    def __init__(self, scenario: Scenario, options: DaemonOptions) -> None:
        ctx = self.ctx = MissionContext(scenario, options)
        self.scenario, self.steps, self.n = scenario, ctx.steps, ctx.n
        self.account = ctx.account  # the mission's counters (a checkpoint saves and restores)
        self.vehicle = ctx.vehicle
        self.tlog: TlogWriter | None = None
        self.fingerprint = mission_fingerprint(scenario, options.seed, self.n, self.steps)
        self.checkpoints = (
            None
            if options.checkpoint_path is None
            else CheckpointWriter(
                options.checkpoint_path,
                self.fingerprint,
                background=True,
                key=options.signing_key,
                role=options.checkpoint_role,
            )
        )
        self.phase = "connect"  # the phase the mission is in (launch phase names, "decisions")
        self.step_wall_s: float | None = None  # paced time: a step's computation, calibrated
        #: safety judged along every position report (track_audit.py), not only at decisions
        self.audit = TrackAudit(
            self.n,
            ctx.envelope.threat_xy_km,
            ctx.envelope.threat_radius_km,
            scenario.config.min_separation_km,
            max_gap_s=scenario.config.step_s,
            project=lambda lat, lon: geodetic_to_local_km(lat, lon, scenario.origin),
        )
        self.report: MissionReport | None = None  # set on every way out of fly()
        self.started = time.monotonic()
        #: one vehicle's failure stays one vehicle's: lost and rejoined (vehicle_loss.py)
        self.loss = LossWatch(
            ctx.vehicles,
            ctx.account,
            options.lost_after_s,
            in_mission=lambda: self.phase == "decisions",
            say=ctx.say,
            pauses=SwarmPauses() if options.lockstep else None,
        )
        self.home = FlightHomePhase(ctx)  # who flies home how (flight_home.py)
        #: the launch, in order; a phase is added here (launch.LaunchPhase), not in fly()
        self.launch: list[LaunchPhase] = launch_phases()
        self.launching = Launch(ctx, self.home, self.loss)
        #: what an operator asks from the mission view (operator_actions.py): ``operator.inbox``
        self.operator = OperatorActions(ctx, self.home, self.loss)
        self.loop = DecisionLoop(ctx, self.home, self.audit, self.watch_links, self.operator)
        #: the planner's factory ``(scenario, starts, seed)``, built once the link is up (None:
        #: HAPF-ACO over the whole fleet); a planner node's plans its one UAV over the swarm link
        #: (given None: a planner attached to no link, the template a checkpoint is checked
        #: against)
        self.planner_factory: Callable[[SwarmLink | None], Any] | None = None

    @property
    def options(self) -> DaemonOptions:
        return self.ctx.options

    @property
    def link(self) -> SwarmLink | None:
        return self.ctx.link

    @property
    def resume_from(self) -> Checkpoint | None:
        """The checkpoint this daemon resumes from (``prepare``; None: a fresh mission)."""
        return self.launching.resume_from

    @property
    def take_back(self) -> list[TakeBack]:
        """A resumed daemon's decision for each plane (resume_takeback.py)."""
        return self.launching.take_back

    def close(self) -> None:
        if self.checkpoints is not None:
            try:
                self.checkpoints.flush()  # the last step's checkpoint is on disk before we go
            except CheckpointError as exc:
                self.ctx.say(f"warning: {exc}")
        if self.ctx.link is not None:
            self.ctx.link.close()
        if self.tlog is not None:
            self.tlog.close()

    # ------------------------------------------------------------------ link and clock

    def connect(self) -> SwarmLink:
        ctx, options = self.ctx, self.ctx.options
        if options.tlog_path is not None:
            self.tlog = TlogWriter(options.tlog_path, append=options.resume)
        expected = set(ctx.keys)
        # our heartbeat at 1 Hz of the vehicles' clock (at 10x, every 0.1 s of wall time): an
        # autopilot's GCS failsafe counts its own seconds without one
        beat_s = 1.0 if options.lockstep else max(0.05, 1.0 / options.time_scale)
        limits = PlausibilityLimits(
            max_ground_speed_mps=2.0 * ctx.plane.max_speed_mps,
            move_after_s=options.lost_after_s,
            time_scale=ctx.time_scale,
            lockstep=options.lockstep,
        )
        link = ctx.link = SwarmLink.open(
            ctx.endpoint_specs,
            self.tlog,
            links=ctx.links(),
            heartbeat_period_s=min(1.0, beat_s),
            accept_vehicle=lambda key: key in expected,
            signing_key=options.signing_key,
            plausibility=PlausibilityFilter(limits),
            may_move=self.gone,
            source=options.source,
        )
        if options.lockstep:
            ctx.clock = LockstepClock(link, ctx.scenario.config.step_s)
        link.listeners.append(
            position_listener(
                self.audit, None if options.lockstep else ctx.time_scale, ctx.index_of
            )
        )
        return link

    def watch_links(self, step: int) -> None:
        """Loss and return (``vehicle_loss.LossWatch``), at every pump of the loop; and the
        lines the plausibility filter has to say (a clock restarted, an address moved)."""
        self.say_notices()
        self.loss.watch(step)

    def gone(self, v: VehicleState) -> bool:
        """Vehicle ``v`` counts as gone (lost to silence or a closed link; a whole-swarm pause
        of a lockstep simulator is no one's silence): only then may its address move."""
        return self.loss.reasons.get(self.ctx.index_of(v.key), "").startswith(GONE)

    def say_notices(self) -> None:
        """Say, once each, the lines the plausibility filter has to say (a clock restarted, an
        address moved, a second address refused)."""
        notices = self.ctx.require_link().plausibility.notices
        while notices:
            self.ctx.say(f"warning: {notices.pop(0)}")

    # ------------------------------------------------------------------ the mission

    def checkpoint_template(self) -> dict[str, Any]:
        """What a checkpoint of this mission must look like (``checkpoint.load_for_mission``):
        the loop state this daemon starts from (at the scenario's starts: the layout is the
        same) and, under ``daemon``, its counters."""
        planner_cls, recorder_cls = _import_planner()
        if self.planner_factory is not None:  # (a planner node's, not attached to a link)
            planner_cls = self.planner_factory(None)
        fallback = self.scenario.starts_for_seed(self.options.seed)
        starts = tuple(
            fallback[u] if u < len(fallback) else UavStart(0.5, 0.5, 0.0) for u in self.ctx.fleet
        )
        state = self.loop.start_state(planner_cls, recorder_cls, starts, [-1] * self.n)
        counters = {name: getattr(self.account, name) for name in DAEMON_STATE}
        return {**state.checkpoint_view(), "daemon": counters}

    def prepare(self) -> SwarmLink:
        """What can fail before any vehicle is touched: the checkpoint to resume from, a time
        scale this machine cannot keep, then the endpoints. Called by :meth:`fly`; a caller may
        call it first, to fail before it shows anything else (each failure is one line)."""
        options = self.options
        if options.resume and self.resume_from is None:
            if options.checkpoint_path is None:
                raise UserError("--resume needs --checkpoint PATH (the file to resume from)")
            self.launching.resume_from = load_for_mission(
                options.checkpoint_path,
                self.fingerprint,
                self.checkpoint_template(),
                options.signing_key,
                options.checkpoint_role,
            )
        writer = self.checkpoints
        if writer is not None and writer.key is None and not writer.announced:
            writer.announced = True  # (once: a caller may call prepare first)
            self.ctx.say(
                f"note: checkpoint {options.checkpoint_path} is not authenticated (no "
                f"signing key): anyone who can write it can change what --resume does"
            )
        self.refuse_unkeepable_time_scale()
        return self.ctx.link if self.ctx.link is not None else self.connect()

    def enter(self, phase: str) -> None:
        """Note the phase the mission is in (for its exit report and the loss watch)."""
        self.phase = phase

    def fly(self) -> MissionReport:
        """Run the launch, the decision loop and RTL; return the result measured over MAVLink.

        Every way out (the end, an error, Ctrl-C, SIGTERM raised as :class:`MissionInterrupted`)
        goes through :meth:`finish`: RTL to every airborne vehicle still reachable, said and
        listed, and the result of what was flown (``self.report``, also when the exception is
        re-raised: the caller writes it)."""
        HapfAcoPlanner, MissionRecorder = _import_planner()
        self.started = time.monotonic()
        self.prepare()
        try:
            run_launch(self.launching, self.launch, self.enter, self.say_notices)
            self.enter("decisions")
            self.audit.set_phase("mission")
            planner = HapfAcoPlanner
            if self.planner_factory is not None:
                planner = self.planner_factory(self.ctx.require_link())
            self.loop.run(
                planner,
                MissionRecorder,
                self.resume_from,
                self.take_back,
                self.checkpoints,
                lambda: time.monotonic() - self.started,
            )
        except BaseException as exc:
            self.finish(ended_by(exc))
            raise
        return self.finish(self.loop.ended_early or "completed")

    def refuse_unkeepable_time_scale(self) -> None:
        """Paced time: calibrate a step's computation on this machine and refuse, in one line,
        a time scale it cannot keep (``keeping_up.py``); once, before any vehicle is touched."""
        if self.options.lockstep or self.step_wall_s is not None:
            return
        if not self.options.check_time_scale:
            return
        from planner.hapf_aco import HapfAcoPlanner

        ctx = self.ctx
        self.step_wall_s = measure_step_wall_s(
            ctx.scenario, ctx.options.seed, HapfAcoPlanner, ctx.envelope, ctx.flight_envelope
        )
        refuse_unkeepable_time_scale(ctx.time_scale, ctx.scenario.config.step_s, self.step_wall_s)

    def finish(self, ended: str) -> MissionReport:
        """The one exit path: RTL to every airborne vehicle still reachable (never to a grounded,
        disarmed one), say to whom, release a lockstep simulator, close the link and the tlog,
        and keep the result of what was flown in ``self.report``. Never raises: a dead socket
        or an unanswered command is a warning line."""
        where = self.phase
        self.operator.inbox.close(f"the mission is over ({ended})")
        self.enter("rtl")
        self.audit.set_phase("rtl")
        sent_to: list[int] = []
        skipped: dict[int, str] = {}
        completed = ended.startswith("completed")
        stages = self.loop.stages
        try:
            self.operator.watched_home()  # the planes it sent home: watched like the others
            # a daemon that does not stay to watch the flight home (interrupted, or
            # ``--rtl-watch 0``) holds no plane: nobody would release it
            watched = completed and self.options.rtl_watch_s != 0
            sent_to, skipped = self.home.return_to_launch(
                None if stages is None else stages.end_leg_timing, separate=watched
            )
            if completed:  # (an interrupted daemon does not stay to watch)
                watch_flight_home(self.home)
        except Exception as exc:  # noqa: BLE001 - the cleanup goes on whatever happens
            self.ctx.say(f"warning: RTL could not be sent to every vehicle ({exc})")
        self.audit.end()  # the account ends with the watch, before the simulator runs free
        with contextlib.suppress(Exception):
            self.ctx.release_clock()
        try:
            result = self.result_so_far(ended, where)
        except Exception as exc:  # noqa: BLE001 - a result of what is known, whatever happens
            self.loop.state = None
            result = self.result_so_far(f"{ended} (no flight result: {exc})", where)
        result.update(self.home.result(sent_to, skipped))
        result["track_audit"] = self.audit.summary()
        self.close()
        self.report = MissionReport(result, self.account.events)
        return self.report

    def result_so_far(self, ended: str, phase: str) -> dict[str, Any]:
        """The result of what was flown: the recorder's (every recorded step), with the MAVLink
        fields, how the mission ended and in which phase. Before the first step there is no
        recorder: only the MAVLink fields (``steps`` 0)."""
        extra = mavlink_extra(
            self.account,
            self.ctx.require_link(),
            str(self.options.tlog_path) if self.options.tlog_path else None,
            None if self.resume_from is None else self.resume_from.step,
            [key.label() for key in self.ctx.keys],
        )
        extra["ended"] = ended
        extra["ended_in_phase"] = phase
        if self.take_back:
            extra["resume_decisions"] = [t.row() for t in self.take_back]
        extra.update(self.operator.result())
        hold = self.loop.hold_policy
        if hold is not None:
            extra["held_steps"] = hold.held_steps
            extra["max_lateness_s"] = round(hold.max_lateness_s, 2)
            extra["calibrated_step_wall_s"] = self.step_wall_s
        wall_s = time.monotonic() - self.started
        state = self.loop.state
        if state is None:
            return {
                "scenario": self.scenario.name,
                "algorithm": ALGORITHM,
                "seed": self.options.seed,
                "steps": 0,
                "wall_time_s": wall_s,
                **extra,
            }
        log = PursuitLog.of(state.planner)
        if log is not None:  # joined with a simulator's truth by swarmplan demo / account
            extra["planner_facts"] = log.facts()
        extra["look_times_ms"] = self.loop.look_times.rows()
        extra["planned_with"] = state.planner.cfg.changed_from(self.scenario.config)
        return state.recorder.result(self.options.seed, ALGORITHM, wall_s, extra=extra)


__all__ = [
    "MIN_RETRY_S",
    "STEP_SENDS",
    "DaemonOptions",
    "MissionDaemon",
    "MissionReport",
    "StepRecord",
    "StepStatus",
    "mavlink",
]
