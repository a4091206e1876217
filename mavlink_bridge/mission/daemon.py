"""The planner daemon: flies a swarm of MAVLink vehicles with the HAPF-ACO planner.

One mission, in order:

1. the launch (``launch.py``): discover every expected system id, wait until each
   autopilot is ready, upload the threat zones as fence exclusion circles, arm, take off, GUIDED,
   ask for the homes;
2. the decision loop: every step waits for its decision instant (``pacing.py``), then runs its
   stages (``decision_step.py``): gather each UAV's inputs, plan, flight envelope, record,
   command batch, send (acknowledged, retried), account; step listeners get a read-only
   :class:`~mavlink_bridge.results.mission_result.StepRecord`;
3. the one exit path, also on an error, Ctrl-C or SIGTERM (:meth:`MissionDaemon.finish`): RTL to
   every airborne vehicle still reachable (``rtl_at_exit.py``), the result of what was flown.

A vehicle whose link went away, silent for ``lost_after_s``, or (in the loop) disarmed or out of
GUIDED is lost (inactive to the planner; the others go on) and rejoins when it is back
(``vehicle_loss.py``). What is recorded comes from what came back over MAVLink: positions from
the looks / telemetry, engagements from their acknowledged outcomes (``mission_result.py``).
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from mavlink_bridge.mission.decision_step import DecisionStep, LoopState, course_heading
from mavlink_bridge.mission.flown_planning import flight_margin_km, planning_scenario
from mavlink_bridge.mission.keeping_up import (
    HoldWhenLate,
    held_apart,
    measure_step_wall_s,
    refuse_unkeepable_time_scale,
)
from mavlink_bridge.mission.launch import LaunchPhase, launch_phases, run_launch
from mavlink_bridge.mission.lockstep_clock import LockstepClock, SwarmPauses
from mavlink_bridge.mission.pacing import (
    STEP_DEADLINE_SHARE,
    DecisionInstant,
    PacingChoice,
    PacingContext,
)
from mavlink_bridge.mission.resume_takeback import CONTINUE, LAUNCH, TakeBack, account_outage
from mavlink_bridge.results.checkpoint import (
    DAEMON_STATE,
    Checkpoint,
    CheckpointError,
    CheckpointWriter,
    load_for_mission,
    mission_fingerprint,
    resume_loop_state,
)
from mavlink_bridge.results.mission_result import (
    ALGORITHM,
    LinkEvent,
    LookTimes,
    MissionAccount,
    MissionReport,
    StepListener,
    StepRecord,
    StepStatus,
    mavlink_extra,
)
from mavlink_bridge.safety.flight_envelope import FlightEnvelope
from mavlink_bridge.safety.safety_envelope import SafetyEnvelope
from mavlink_bridge.safety.track_audit import TrackAudit, position_listener
from mavlink_bridge.vehicles.airframe import (
    MAX_THREAT_MARGIN_KM,
    Airframe,
    fleet_plane_model,
    scenario_plane_model,
    threat_margin_km,
)
from mavlink_bridge.vehicles.guided_commands import (
    Command,
    send_commands,
)
from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_bridge.vehicles.telemetry_plausibility import PlausibilityFilter, PlausibilityLimits
from mavlink_bridge.vehicles.vehicle_loss import GONE, LossWatch
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_bridge.way_home.flight_home import (
    FlightHome,
    guide_sent_home,
    guide_stray_returns,
    reposition_to,
    return_separation,
    return_to_launch,
    watch_rtl,
)
from mavlink_wire.protocol import mavlink
from mavlink_wire.tlog import TlogWriter
from planner.errors import UserError
from planner.geodesy import geodetic_to_local_km, local_km_to_geodetic
from planner.grid import Grid, heading_of_angle
from planner.pursuit_log import PursuitLog
from planner.scenario import Scenario, UavStart

#: a decision step's commands are sent this many times before its deadline when unanswered
#: (``MissionDaemon.send``), resent no faster than every ``MIN_RETRY_S`` of wall time
STEP_SENDS = 5
MIN_RETRY_S = 0.02


@dataclass
class DaemonOptions:
    """Everything a mission run needs besides the scenario."""

    connect: list[str]
    seed: int = 0
    expect: int | None = None  # vehicles expected (system ids 1..N); default: the scenario's UAVs
    steps: int | None = None  # decision steps; default: the scenario's
    discovery_timeout_s: float = 60.0
    ready_timeout_s: float = 120.0
    lost_after_s: float = 3.0  # wall seconds of silence before a vehicle counts as lost
    takeoff_altitude_m: float = 30.0  # climb (above home) that ends the TAKEOFF phase
    #: steps the planner keeps back for the way home beyond the scenario's
    #: ``home_reserve_steps``: the flight envelope's replacements on the way cost some
    #: (docs/parameters.md, "Home by mission end")
    home_reserve_extra_steps: int = 3
    takeoff_timeout_s: float = 60.0
    #: the safety envelope's clearance of every leg from the threat circles; None: from the
    #: airframe read at launch (``airframe.threat_margin_km``: its loiter circle plus
    #: ``predicted_threat_margin_km``, at most 1 km; 1 km until then, and for the simulator's
    #: 100 m/s plane, about its minimum turn radius)
    threat_margin_km: float | None = None
    separation_margin_km: float = 1.0  # on top of d_min: telemetry positions lag the cells
    #: guided targets lead the next cell by this many legs along the planned direction, so a
    #: plane passes through the cell centre on time instead of arriving and circling it
    lead_steps: float = 1.0
    #: the flight-path envelope (flight_envelope.py): predict each plane's path this many
    #: decision steps ahead (0 turns it off) and keep it clear of threats and of the other
    #: planes' paths
    prediction_horizon_steps: float = 3.0
    predicted_threat_margin_km: float = 0.25
    predicted_separation_margin_km: float = 0.3
    #: bank limit of the predicted turns; None: each airframe's own (ROLL_LIMIT_DEG / FW_R_LIM,
    #: read at launch by mavlink_bridge/vehicles/airframe.py; 45 deg until then)
    bank_limit_deg: float | None = None
    #: fly each leg in one decision step, as the paper's grid does (a diagonal cell at sqrt(2) v):
    #: an airspeed per leg (MAV_CMD_DO_CHANGE_SPEED) within ``airspeed_range_mps``; off, every
    #: plane flies the scenario's speed and falls behind the grid on diagonal legs
    leg_timing: bool = True
    #: slowest and fastest airspeed asked for; default v .. 1.5 v (within the simulator's
    #: AIRSPEED_MIN/MAX; set it to your airframe's envelope). Below v a plane turns more than
    #: phi_max in one step (see flight_prediction.PlaneModel.min_speed_mps)
    airspeed_range_mps: tuple[float, float] | None = None
    max_refusals: int = 5  # consecutive refused guided targets of one vehicle that end the run
    #: measured legs come from telemetry, not cell centres: a turn counts as a C_m violation only
    #: beyond phi_max plus this (the envelope itself never commands more than phi_max)
    turn_tolerance_deg: float = 15.0
    #: vehicles' clock speed: the step deadline until it is measured; steps only by the wall
    #: clock at this speed for vehicles that report no time at all (pacing.py)
    time_scale: float = 1.0
    #: the vehicles are ``swarmplan sim --lockstep``: grant simulated time one decision period at
    #: a time (mavlink_bridge/mission/lockstep_clock.py); the run is then repeatable for a seed
    lockstep: bool = False
    command_retry_s: float = 0.3
    command_attempts: int = 5
    #: arm / mode commands of the launch are not time-critical: try them longer over a lossy link
    launch_command_attempts: int = 12
    #: write the planner and loop state here after every step (mavlink_bridge/results/checkpoint.py)
    checkpoint_path: Path | None = None
    resume: bool = False  # carry on from checkpoint_path instead of starting afresh
    signing_key: bytes | None = None  # MAVLink 2 signing (mavlink_wire/signing.py)
    tlog_path: Path | None = None
    progress: Callable[[str], None] | None = None
    on_step: Callable[[StepStatus], None] | None = None
    #: called after every decision step with a read-only snapshot (mission_result.StepRecord)
    step_listeners: list[StepListener] = field(default_factory=list)
    #: after RTL, keep listening (in lockstep: granting time) until every vehicle circles its
    #: home, at most this many of the vehicles' seconds (None: the flight home of the farthest
    #: plus two minutes; 0: not at all), so the flight home is in the continuous account too
    rtl_watch_s: float | None = None
    #: paced time: a step more than this many of the vehicles' seconds late sends no new
    #: targets, the planes circle their last (safe) ones (keeping_up.py); None: one decision
    #: period
    late_bound_s: float | None = None
    #: paced time: refuse at start a time scale the calibration says this machine cannot keep
    #: (keeping_up.py); off only for tests of other things that run deliberately too fast
    check_time_scale: bool = True


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
        self.scenario = scenario
        self.options = options
        cfg = scenario.config
        self.grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
        self.n = options.expect or scenario.uav_count
        if self.n <= 0:
            raise UserError("--expect must be at least 1")
        self.system_ids = list(range(1, self.n + 1))
        self.steps = options.steps or scenario.steps
        self.envelope = SafetyEnvelope.for_scenario(
            scenario,
            MAX_THREAT_MARGIN_KM if options.threat_margin_km is None else options.threat_margin_km,
            options.separation_margin_km,
        )
        self.account = MissionAccount()
        #: each step's look time stamps, to join a simulator's truth (the per-target account)
        self.look_times = LookTimes()
        self.tlog: TlogWriter | None = None
        self.link: SwarmLink | None = None
        #: the airframe flown (airframe.py): the scenario's until the vehicles' are read
        self.plane = scenario_plane_model(cfg, options.airspeed_range_mps, options.bank_limit_deg)
        self.flight_envelope = (
            FlightEnvelope(
                self.envelope,
                self.plane,
                step_s=cfg.step_s,
                horizon_steps=options.prediction_horizon_steps,
                threat_margin_km=options.predicted_threat_margin_km,
                separation_margin_km=options.predicted_separation_margin_km,
                leg_timing=options.leg_timing,
                # paced: a lost target is resent until the step's deadline (lossy links)
                command_delay_s=0.0 if options.lockstep else STEP_DEADLINE_SHARE * cfg.step_s,
            )
            if options.prediction_horizon_steps > 0
            else None
        )
        self.flight_home = FlightHome()  # who flies home how (flight_home.py)
        self._target_values = {t.id: float(t.value) for t in scenario.targets}
        self.fingerprint = mission_fingerprint(scenario, options.seed, self.n, self.steps)
        self.checkpoints = (
            None
            if options.checkpoint_path is None
            else CheckpointWriter(
                options.checkpoint_path, self.fingerprint, background=True, key=options.signing_key
            )
        )
        self.resume_from: Checkpoint | None = None
        #: a resumed daemon's decision for each plane (resume_takeback.py)
        self.take_back: list[TakeBack] = []
        self.clock: LockstepClock | None = None
        self.pacing: PacingChoice | None = None
        self.stages: DecisionStep | None = None
        #: the launch, in order; a phase is added here (mission_launch.LaunchPhase), not in fly()
        self.launch: list[LaunchPhase] = launch_phases()
        self.phase = "connect"  # the phase the mission is in (launch phase names, "decisions")
        self.step_wall_s: float | None = None  # paced time: a step's computation, calibrated
        #: held planes no point keeps d_min apart (said once: ``hold_apart``)
        self.stuck_in_hold: set[int] = set()
        #: paced time: hold the planes at their last safe targets while late (keeping_up.py)
        self.hold_policy = (
            None
            if options.lockstep
            else HoldWhenLate(
                cfg.step_s,
                cfg.step_s if options.late_bound_s is None else options.late_bound_s,
                self.say,
            )
        )
        #: safety judged along every position report (track_audit.py), not only at decisions
        self.audit = TrackAudit(
            self.n,
            self.envelope.threat_xy_km,
            self.envelope.threat_radius_km,
            cfg.min_separation_km,
            max_gap_s=cfg.step_s,
            project=lambda lat, lon: geodetic_to_local_km(lat, lon, scenario.origin),
        )
        self.state: LoopState | None = None  # the decision loop's, once it runs
        self.ended_early: str | None = None  # why the mission ended before its last step
        self.report: MissionReport | None = None  # set on every way out of fly()
        self.started = time.monotonic()
        #: one vehicle's failure stays one vehicle's: lost and rejoined (vehicle_loss.py)
        self.loss = LossWatch(
            self.vehicles,
            self.account,
            options.lost_after_s,
            in_mission=lambda: self.phase == "decisions",
            say=self.say,
            pauses=SwarmPauses() if options.lockstep else None,
        )

    # ------------------------------------------------------------------ the daemon's counters
    # (attributes of the account; a checkpoint reads and restores them by these names)

    @property
    def overrides(self) -> dict[str, int]:
        return self.account.overrides

    @overrides.setter
    def overrides(self, value: dict[str, int]) -> None:
        self.account.overrides = value

    @property
    def refused_commands(self) -> int:
        return self.account.refused_commands

    @refused_commands.setter
    def refused_commands(self, value: int) -> None:
        self.account.refused_commands = value

    @property
    def looks_missed(self) -> int:
        return self.account.looks_missed

    @looks_missed.setter
    def looks_missed(self, value: int) -> None:
        self.account.looks_missed = value

    @property
    def late_steps(self) -> int:
        return self.account.late_steps

    @late_steps.setter
    def late_steps(self, value: int) -> None:
        self.account.late_steps = value

    @property
    def events(self) -> list[LinkEvent]:
        return self.account.events

    @events.setter
    def events(self, value: list[LinkEvent]) -> None:
        self.account.events = value

    # ------------------------------------------------------------------ helpers

    def say(self, text: str) -> None:
        if self.options.progress is not None:
            self.options.progress(text)

    def require_link(self) -> SwarmLink:
        assert self.link is not None, "connect() first"
        return self.link

    def vehicle(self, uav: int) -> VehicleState:
        return self.require_link().vehicles[uav + 1]

    def vehicles(self) -> list[VehicleState]:
        """The expected vehicles, index = UAV (each heard at least once)."""
        return [self.vehicle(i) for i in range(self.n)]

    def local_km(self, lat: float, lon: float) -> np.ndarray:
        x, y = geodetic_to_local_km(lat, lon, self.scenario.origin)
        return np.array([x[0], y[0]])

    def geodetic(self, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xy = self.grid.centre_km(cells)
        return local_km_to_geodetic(xy[:, 0], xy[:, 1], self.scenario.origin)

    def send(
        self,
        commands: list[Command],
        attempts: int | None = None,
        deadline: float | None = None,
    ) -> list[Command]:
        """Send and resend until acknowledged. In lockstep simulated time waits for us, so a
        command is resent for as long as a vehicle may stay silent before it counts as lost
        (``lost_after_s``), not just ``command_attempts`` times: on a lossy link a guided
        target that never arrives would leave the plane flying the previous leg. In paced time
        the vehicles fly on meanwhile, so a decision step stops waiting at ``deadline``: what is
        unanswered then is sent again at the next step. Before a deadline a command is resent
        often enough to be sent ``STEP_SENDS`` times (every ``command_retry_s`` at most, every
        ``MIN_RETRY_S`` at least): at 20x the deadline is 0.3 s of wall time, one send at the
        0.3 s retry, and at 30 % loss each way a third of the planes' targets did not arrive
        within their step (they flew on to the previous one for the whole step). Without a
        deadline (the launch), vehicles faster than the wall clock get their resends as often
        in their own time, over the same wall-clock window."""
        opts = self.options
        retry_s = opts.command_retry_s
        if attempts is None:
            attempts = opts.command_attempts
            if opts.lockstep:
                attempts = max(attempts, math.ceil(opts.lost_after_s / opts.command_retry_s))
        if deadline is not None:
            window_s = max(0.0, deadline - time.monotonic())
            retry_s = min(retry_s, max(MIN_RETRY_S, window_s / STEP_SENDS))
            attempts = max(attempts, math.ceil(window_s / retry_s) + 1)
        elif not opts.lockstep and self.time_scale > 1.0:
            # vehicles flying faster than the wall clock (a simulator, SITL): resent as often in
            # their time, over the same wall-clock window. At 20x a lost switch to GUIDED was
            # resent after 6 s of flight, and a plane flew its take-off's straight line 3.5 km
            # to the edge of a threat ahead before the mission began (30 % loss each way)
            fast_s = max(MIN_RETRY_S, retry_s / self.time_scale)
            attempts = math.ceil(attempts * retry_s / fast_s)
            retry_s = fast_s
        return send_commands(self.require_link(), commands, retry_s, attempts, deadline)

    def use_airframes(self, airframes: list[Airframe]) -> None:
        """Fly the airframes read at launch: the plane model of the flight prediction and the
        leg timing (turn radius from their bank limit, airspeed range, loiter radius);
        ``--airspeed-range`` and ``bank_limit_deg`` given by the user still win."""
        self.plane = fleet_plane_model(
            airframes,
            self.scenario.config,
            self.options.airspeed_range_mps,
            self.options.bank_limit_deg,
        )
        if self.options.threat_margin_km is None:
            margin = threat_margin_km(self.plane, self.options.predicted_threat_margin_km)
            self.envelope = replace(self.envelope, threat_margin_km=margin)
        if self.flight_envelope is not None:
            self.flight_envelope = replace(
                self.flight_envelope, model=self.plane, cells=self.envelope
            )

    # ------------------------------------------------------------------ link and clock

    def connect(self) -> SwarmLink:
        if self.options.tlog_path is not None:
            self.tlog = TlogWriter(self.options.tlog_path, append=self.options.resume)
        expected = set(self.system_ids)
        # our heartbeat at 1 Hz of the vehicles' clock (at 10x, every 0.1 s of wall time): an
        # autopilot's GCS failsafe counts its own seconds without one
        beat_s = 1.0 if self.options.lockstep else max(0.05, 1.0 / self.options.time_scale)
        limits = PlausibilityLimits(
            max_ground_speed_mps=2.0 * self.plane.max_speed_mps,
            move_after_s=self.options.lost_after_s,
            time_scale=self.time_scale,
            lockstep=self.options.lockstep,
        )
        self.link = SwarmLink.open(
            self.options.connect,
            self.tlog,
            heartbeat_period_s=min(1.0, beat_s),
            accept_system_id=lambda s: s in expected,
            signing_key=self.options.signing_key,
            plausibility=PlausibilityFilter(limits),
            may_move=self.gone,
        )
        if self.options.lockstep:
            self.clock = LockstepClock(self.link, self.scenario.config.step_s)
        self.link.listeners.append(
            position_listener(self.audit, None if self.options.lockstep else self.time_scale)
        )
        return self.link

    def wait_sim(self, done: Callable[[], bool], timeout_s: float) -> bool:
        """Pump until ``done()``; against a lockstep simulator grant simulated time meanwhile
        (``timeout_s`` then counts simulated seconds)."""
        link = self.require_link()
        if self.clock is None:
            return link.pump_until(done, timeout_s)
        return self.clock.run_until(done, self.vehicles(), timeout_s)

    def release_clock(self) -> None:
        """Lockstep over: let the simulator run on its own (the vehicles fly their RTL)."""
        if self.clock is not None and self.link is not None:
            self.clock.release(list(self.link.vehicles.values()))

    def watch_links(self, step: int) -> None:
        """Loss and return (``vehicle_loss.LossWatch``), at every pump of the loop; and the
        lines the plausibility filter has to say (a clock restarted, an address moved)."""
        self.say_notices()
        self.loss.watch(step)

    def gone(self, v: VehicleState) -> bool:
        """Vehicle ``v`` counts as gone (lost to silence or a closed link; a whole-swarm pause
        of a lockstep simulator is no one's silence): only then may its address move."""
        return self.loss.reasons.get(v.system_id - 1, "").startswith(GONE)

    def say_notices(self) -> None:
        """Say, once each, the lines the plausibility filter has to say (a clock restarted, an
        address moved, a second address refused)."""
        notices = self.require_link().plausibility.notices
        while notices:
            self.say(f"warning: {notices.pop(0)}")

    # ------------------------------------------------------------------ the mission

    def prepare(self) -> SwarmLink:
        """What can fail before any vehicle is touched: the checkpoint to resume from, a time
        scale this machine cannot keep, then the endpoints. Called by :meth:`fly`; a caller may
        call it first, to fail before it shows anything else (each failure is one line)."""
        if self.options.resume and self.resume_from is None:
            if self.options.checkpoint_path is None:
                raise UserError("--resume needs --checkpoint PATH (the file to resume from)")
            self.resume_from = load_for_mission(
                self.options.checkpoint_path,
                self.fingerprint,
                self.checkpoint_template(),
                self.options.signing_key,
            )
        writer = self.checkpoints
        if writer is not None and writer.key is None and not writer.announced:
            writer.announced = True  # (once: a caller may call prepare first)
            self.say(
                f"note: checkpoint {self.options.checkpoint_path} is not authenticated (no "
                f"signing key): anyone who can write it can change what --resume does"
            )
        self.refuse_unkeepable_time_scale()
        return self.link if self.link is not None else self.connect()

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
            run_launch(self, self.launch)
            self.phase = "decisions"
            self.audit.set_phase("mission")
            self.decision_loop(HapfAcoPlanner, MissionRecorder)
        except BaseException as exc:
            self.finish(ended_by(exc))
            raise
        return self.finish(self.ended_early or "completed")

    def refuse_unkeepable_time_scale(self) -> None:
        """Paced time: calibrate a step's computation on this machine and refuse, in one line,
        a time scale it cannot keep (``keeping_up.py``); once, before any vehicle is touched."""
        if self.options.lockstep or self.step_wall_s is not None:
            return
        if not self.options.check_time_scale:
            return
        from planner.hapf_aco import HapfAcoPlanner

        self.step_wall_s = measure_step_wall_s(
            self.scenario, self.options.seed, HapfAcoPlanner, self.envelope, self.flight_envelope
        )
        refuse_unkeepable_time_scale(self.time_scale, self.scenario.config.step_s, self.step_wall_s)

    @property
    def time_scale(self) -> float:
        return max(self.options.time_scale, 1e-6)

    def finish(self, ended: str) -> MissionReport:
        """The one exit path: RTL to every airborne vehicle still reachable (never to a grounded,
        disarmed one), say to whom, release a lockstep simulator, close the link and the tlog,
        and keep the result of what was flown in ``self.report``. Never raises: a dead socket
        or an unanswered command is a warning line."""
        where = self.phase
        self.phase = "rtl"
        self.audit.set_phase("rtl")
        sent_to: list[int] = []
        skipped: dict[int, str] = {}
        # an interrupted daemon does not stay to watch the flight home, so holds no plane
        flight = self.flight_home
        completed = ended.startswith("completed")
        flight.separate = completed
        try:
            sent_to, skipped = return_to_launch(self)
            if completed:  # (an interrupted daemon does not stay to watch)
                watch_rtl(self)
        except Exception as exc:  # noqa: BLE001 - the cleanup goes on whatever happens
            self.say(f"warning: RTL could not be sent to every vehicle ({exc})")
        self.audit.end()  # the account ends with the watch, before the simulator runs free
        with contextlib.suppress(Exception):
            self.release_clock()
        try:
            result = self.result_so_far(ended, where)
        except Exception as exc:  # noqa: BLE001 - a result of what is known, whatever happens
            self.state = None
            result = self.result_so_far(f"{ended} (no flight result: {exc})", where)
        # a vehicle guided around threats got its RTL during the watch, once the way was clear
        later = (flight.detoured | flight.held) - set(flight.homing) - set(flight.holding)
        result["rtl_sent_to"] = sorted(set(sent_to) | later)
        result["guided_home_around_threats"] = sorted(flight.detoured)
        result["held_for_separation_home"] = sorted(flight.held)
        result["home_circle_speeds_mps"] = {
            str(k): round(v, 1) for k, v in sorted(flight.circles.speeds_mps.items())
        }
        result["rtl_not_sent"] = {str(k): why for k, why in sorted(skipped.items())}
        result["track_audit"] = self.audit.summary()
        self.close()
        self.report = MissionReport(result, self.events)
        return self.report

    def result_so_far(self, ended: str, phase: str) -> dict[str, Any]:
        """The result of what was flown: the recorder's (every recorded step), with the MAVLink
        fields, how the mission ended and in which phase. Before the first step there is no
        recorder: only the MAVLink fields (``steps`` 0)."""
        extra = mavlink_extra(
            self.account,
            self.require_link(),
            str(self.options.tlog_path) if self.options.tlog_path else None,
            None if self.resume_from is None else self.resume_from.step,
        )
        extra["ended"] = ended
        extra["ended_in_phase"] = phase
        if self.take_back:
            extra["resume_decisions"] = [t.row() for t in self.take_back]
        if self.hold_policy is not None:
            extra["held_steps"] = self.hold_policy.held_steps
            extra["max_lateness_s"] = round(self.hold_policy.max_lateness_s, 2)
            extra["calibrated_step_wall_s"] = self.step_wall_s
        wall_s = time.monotonic() - self.started
        if self.state is None:
            return {
                "scenario": self.scenario.name,
                "algorithm": ALGORITHM,
                "seed": self.options.seed,
                "steps": 0,
                "wall_time_s": wall_s,
                **extra,
            }
        log = PursuitLog.of(self.state.planner)
        if log is not None:  # joined with a simulator's truth by swarmplan demo / account
            extra["planner_facts"] = log.facts()
        extra["look_times_ms"] = self.look_times.rows()
        extra["planned_with"] = self.state.planner.cfg.changed_from(self.scenario.config)
        return self.state.recorder.result(self.options.seed, ALGORITHM, wall_s, extra=extra)

    def close(self) -> None:
        if self.checkpoints is not None:
            try:
                self.checkpoints.flush()  # the last step's checkpoint is on disk before we go
            except CheckpointError as exc:
                self.say(f"warning: {exc}")
        if self.link is not None:
            self.link.close()
        if self.tlog is not None:
            self.tlog.close()

    # ------------------------------------------------------------------ the decision loop

    def starts_from_telemetry(self) -> tuple[UavStart, ...]:
        """Each UAV's start: the cell centre of its home (launch) position, heading from its
        course (nearest of the eight); a vehicle without position falls back to the scenario's."""
        fallback = self.scenario.starts_for_seed(self.options.seed)
        starts = []
        for i in range(self.n):
            v = self.vehicle(i)
            if not v.has_position and v.home is None:
                starts.append(fallback[i] if i < len(fallback) else UavStart(0.5, 0.5, 0.0))
                continue
            lat, lon = (v.home[0], v.home[1]) if v.home is not None else (v.lat_deg, v.lon_deg)
            cell = self.grid.cell_of(self.local_km(lat, lon))
            centre = self.grid.centre_km(cell)
            heading = course_heading(v)
            if heading is None:
                heading = (
                    int(heading_of_angle(math.radians(fallback[i].heading_deg)))
                    if i < len(fallback)
                    else 0
                )
            starts.append(UavStart(float(centre[0]), float(centre[1]), heading * 45.0))
        return tuple(starts)

    _course_heading = staticmethod(course_heading)

    def flight_margin_km(self) -> float:
        """The threat clearance the planner plans every move and the way home with
        (``flown_planning.flight_margin_km``): the flight envelope's for a guided target, its
        loiter circle as flown at cruise plus the predicted margin (2.39 km for the simulator's
        100 m/s plane, 0.41 km for ArduPlane's defaults), at least the cell-level margin.
        Planned at the paper's 0 km, the planner's way home hugged a threat that close and the
        envelope replaced its moves one by one: the plane came home late (paper-10uav demo: 8.2
        of 10 home over seeds 1-6 against 9.9 offline; docs/parameters.md)."""
        fe = self.flight_envelope
        return flight_margin_km(
            self.envelope.threat_margin_km,
            None if fe is None else fe.model,
            0.0 if fe is None else fe.threat_margin_km,
        )

    def planning_scenario(self) -> Scenario:
        """The scenario as this daemon's planner plans it, for the airframes flown: the margins a
        flown plane needs (``flown_planning.planning_scenario``): separation on top of d_min,
        the flight envelope's threat clearance, a few steps more kept back for the way home."""
        return planning_scenario(self.scenario, self.steps, self.options, self.flight_margin_km())

    def make_stages(self) -> DecisionStep:
        """The decision step's stages over the expected vehicles."""
        return DecisionStep(
            scenario=self.scenario,
            grid=self.grid,
            cell_envelope=self.envelope,
            plane=self.plane,
            flight_envelope=self.flight_envelope,
            vehicles=self.vehicles(),
            counters=self.account,
            lead_steps=self.options.lead_steps,
            leg_timing=self.options.leg_timing,
            max_refusals=self.options.max_refusals,
            predict_from_now=self.clock is None,
            clock_rate=self.time_scale,
            send=self.send,
            say=self.say,
            target_values=self._target_values,
        )

    def make_pacing(self) -> PacingChoice:
        ctx = PacingContext(
            link=self.require_link(),
            vehicles=self.vehicles,
            watch=self.watch_links,
            step_s=self.scenario.config.step_s,
            time_scale=self.options.time_scale,
            lost_after_s=self.options.lost_after_s,
            account=self.account,
            say=self.say,
        )
        return PacingChoice(ctx, self.clock)

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
        scenario = self.scenario
        starts = self.starts_from_telemetry() if starts is None else starts
        planner = planner_cls(self.planning_scenario(), starts, self.options.seed)
        PursuitLog().attach(planner)  # the planner's half of the per-target account (read-only)
        recorder = recorder_cls(
            scenario,
            starts,
            turn_tolerance_deg=self.options.turn_tolerance_deg,
            home_reach_km=float(self.plane.loiter_reach_km(self.plane.speed_mps)),
        )
        if consumed is None:
            consumed = [v.latest_look for v in self.vehicles()]
        return LoopState.start(self.grid, planner, recorder, starts, consumed)

    def checkpoint_template(self) -> dict[str, Any]:
        """What a checkpoint of this mission must look like (``checkpoint.load_for_mission``):
        the loop state this daemon starts from (at the scenario's starts: the layout is the
        same) and, under ``daemon``, its counters."""
        planner_cls, recorder_cls = _import_planner()
        fallback = self.scenario.starts_for_seed(self.options.seed)
        starts = tuple(
            fallback[i] if i < len(fallback) else UavStart(0.5, 0.5, 0.0) for i in range(self.n)
        )
        state = self.start_state(planner_cls, recorder_cls, starts, [-1] * self.n)
        counters = {name: getattr(self, name) for name in DAEMON_STATE}
        return {**state.checkpoint_view(), "daemon": counters}

    def first_instant(self) -> DecisionInstant:
        """Step 0 is the start (no wait): its commands are due within the paced deadline."""
        if self.clock is not None:
            return DecisionInstant(0, {}, None, "lockstep")
        period_s = self.scenario.config.step_s / max(self.options.time_scale, 1e-6)
        return DecisionInstant(0, {}, time.monotonic() + STEP_DEADLINE_SHARE * period_s, "start")

    def decision_loop(self, planner_cls: Any, recorder_cls: Any) -> None:
        """The decision steps, from the start (step 0) to ``steps``: wait for the decision
        instant, gather, plan, envelope, record, command batch, send, account, tell listeners,
        checkpoint."""
        state = self.state = self.start_state(planner_cls, recorder_cls)
        stages = self.stages = self.make_stages()
        pacing = self.pacing = self.make_pacing()
        first_step = 0
        if self.resume_from is not None:  # a restarted daemon: the state after its last step
            state = self.state = LoopState.from_checkpoint(
                resume_loop_state(self, self.resume_from, state.planner)
            )
            first_step = self.resume_from.step + 1
            account_outage(state, self.take_back)
            if self.take_back and not any(t.decision in (CONTINUE, LAUNCH) for t in self.take_back):
                self.ended_early = "completed at the resume: no plane can continue (all sent home)"
                self.say(f"mission {self.ended_early}")
                return
        for step in range(first_step, self.steps + 1):  # the start, then one record per step
            instant = pacing.wait(step, state.consumed) if step > 0 else self.first_instant()
            inputs = stages.gather(state, step, instant.looks)
            plan = stages.plan(state, inputs)
            flight = stages.envelope(state, inputs, plan)
            stages.record(state, inputs, plan, flight)
            if step < self.steps:  # the decisions of the mission's steps, as offline counts them
                state.recorder.record_modes(plan.decision.modes)
            batch = stages.command_batch(state, inputs, plan, flight)
            late = pacing.current.late(instant) if step > 0 else False
            if self.holds(step, state, inputs.active):
                self.audit.set_phase("hold")  # nothing new: the planes circle their last targets
                self.hold_apart(state, inputs.active, instant.deadline)
            else:
                self.audit.set_phase("mission")
                sent = self.send(batch.commands, deadline=instant.deadline)
                stages.account(state, step, batch, sent, flight)
            # planes their fence (or a failsafe) switched to RTL through a zone: guided out;
            # planes a resumed daemon sent home: on their safe way home
            homeward = guide_stray_returns(self) + guide_sent_home(self)
            self.send(homeward, deadline=instant.deadline)
            self.look_times.note(step, state.positions_ms, inputs.active)
            self.tell_listeners(state, inputs, plan, flight, late)
            if self.checkpoints is not None:  # atomically, after every step
                self.checkpoints.save(
                    step, self, state.checkpoint_view(), time.monotonic() - self.started
                )
            if plan.done.all() and not self.scenario.config.home_by_end:
                break  # (home_by_end: the mission ends at its last step, as offline)
        self.options = replace(self.options, leg_timing=stages.leg_timing)

    def holds(self, step: int, state: LoopState, active: np.ndarray) -> bool:
        """Paced time: is this step too late to fly (``keeping_up.HoldWhenLate``)?"""
        if self.hold_policy is None or step == 0:
            return False
        return self.hold_policy.hold(step, state.positions_ms, self.vehicles(), active)

    def hold_apart(self, state: LoopState, active: np.ndarray, deadline: float | None) -> None:
        """Held planes whose circles at their last targets would come within d_min of each
        other: one of each pair is moved apart (``keeping_up.held_apart``), and the point it
        accepts becomes its last target. Says who moves, and who no point keeps apart."""
        stages = self.stages
        assert stages is not None
        positions, courses, _speeds, _elapsed = stages.where_now(state, active)
        planes, index = [], {}
        for i, v in enumerate(self.vehicles()):
            target = state.last_target[i]
            if active[i] and target is not None and v.has_position and not v.lost:
                planes.append((v.system_id, positions[i], float(courses[i]), np.array(target)))
                index[v.system_id] = i
        if len(planes) < 2:
            return
        moves, stuck = held_apart(return_separation(self), planes)
        commands = [reposition_to(self, self.vehicle(index[sid]), xy) for sid, xy in moves.items()]
        for c in self.send(commands, deadline=deadline) if commands else []:
            sid = c.vehicle.system_id
            if c.accepted:
                state.last_target[index[sid]] = (float(moves[sid][0]), float(moves[sid][1]))
                self.say(
                    f"vehicle {sid} holds at ({moves[sid][0]:.1f}, {moves[sid][1]:.1f}) km: "
                    "circling its last target it would come within d_min of another held plane"
                )
        for sid in set(stuck) - self.stuck_in_hold:
            self.say(
                f"warning: held vehicle {sid} circles within d_min of another held plane and "
                "no point nearby keeps it apart"
            )
        self.stuck_in_hold = set(stuck)

    def tell_listeners(
        self, state: LoopState, inputs: Any, plan: Any, flight: Any, late: bool
    ) -> None:
        """The progress callback (StepStatus) and the step listeners (StepRecord)."""
        active = inputs.active
        status = StepStatus(
            inputs.step,
            self.steps,
            int(active.sum()),
            [i + 1 for i in range(self.n) if not active[i]],
            float(state.observed.mean()),
            len(state.engaged_ids),
            state.engaged_value,
            sum(self.overrides.values()),
        )
        if self.options.on_step is not None:
            self.options.on_step(status)
        if not self.options.step_listeners:
            return
        record = StepRecord(
            status=status,
            positions_km=state.positions.copy(),
            positions_ms=state.positions_ms.copy(),
            cells=state.cells.copy(),
            headings=state.headings.copy(),
            next_cells=np.array(flight.next_cells, copy=True),
            aims_km=np.array(flight.aims_km, copy=True),
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
        )
        for listener in self.options.step_listeners:
            listener(record)


__all__ = [
    "DaemonOptions",
    "MissionDaemon",
    "MissionReport",
    "StepRecord",
    "StepStatus",
    "mavlink",
]
