"""The planner daemon: flies a swarm of MAVLink vehicles with the HAPF-ACO planner.

One mission, in order:

1. open the endpoints and wait for a heartbeat of every expected system id (``discovery``);
2. wait until each autopilot reports STANDBY (initialisation over);
3. upload the threat zones as fence exclusion circles (``mission_upload``);
4. arm, TAKEOFF mode, wait for the climb, GUIDED;
5. every decision step: take each vehicle's newest sensor look and telemetry as that UAV's
   planner inputs, run the planner, check the next cells against the safety envelope, send the
   engagement requests (camera capture) and the guided targets (COMMAND_INT DO_REPOSITION), each
   with acknowledgement and retry;
6. RTL every vehicle.

A vehicle silent for ``lost_after_s`` is lost (inactive to the planner; the others go on) and
rejoins when heard again. What is recorded comes from what came back over MAVLink: positions from
the looks / telemetry, engagements from their acknowledged outcomes.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from mavlink_bridge.checkpoint import (
    LOOP_STATE,
    Checkpoint,
    CheckpointWriter,
    load_for_mission,
    mission_fingerprint,
    resume_loop_state,
)
from mavlink_bridge.discovery import wait_for_vehicles, wait_until_ready
from mavlink_bridge.flight_envelope import FlightChoice, FlightEnvelope
from mavlink_bridge.flight_prediction import PlaneModel, leg_speed_mps
from mavlink_bridge.guided_commands import (
    Command,
    CommandRefusedError,
    arm_command,
    change_speed_command,
    engagement_command,
    reposition_command,
    request_message_command,
    require_accepted,
    send_commands,
    set_mode_command,
)
from mavlink_bridge.lockstep_clock import LockstepClock
from mavlink_bridge.mission_upload import FenceCircle, upload_fence
from mavlink_bridge.protocol import (
    PLANE_MODE_GUIDED,
    PLANE_MODE_RTL,
    PLANE_MODE_TAKEOFF,
    mavlink,
    result_name,
)
from mavlink_bridge.safety_envelope import EnvelopeDecision, SafetyEnvelope
from mavlink_bridge.sensor_looks import look_report
from mavlink_bridge.swarm_link import SwarmLink
from mavlink_bridge.tlog import TlogWriter
from mavlink_bridge.vehicle_state import Look, VehicleState
from planner.engagement import EngagementOutcome
from planner.errors import UserError
from planner.geodesy import geodetic_to_local_km, local_km_to_geodetic
from planner.grid import Grid, heading_of_angle
from planner.scenario import Scenario, UavStart
from planner.sensor_model import SensorReport

ALGORITHM = "hapf-aco"
#: paced time: share of a decision period the daemon may spend getting a step's commands out
STEP_DEADLINE_SHARE = 0.6


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
    takeoff_timeout_s: float = 60.0
    threat_margin_km: float = 1.0  # about a plane's minimum turn radius at 100 m/s
    separation_margin_km: float = 1.0  # on top of d_min: telemetry positions lag the cells
    #: guided targets lead the next cell by this many legs along the planned direction, so a
    #: plane passes through the cell centre on time instead of arriving and circling it
    lead_steps: float = 1.0
    #: the flight-path envelope (flight_envelope.py): predict each plane's path this far ahead
    #: (simulated s; 0 turns it off) and keep it clear of threats and of the other planes' paths
    prediction_horizon_s: float = 30.0
    predicted_threat_margin_km: float = 0.25
    predicted_separation_margin_km: float = 0.3
    bank_limit_deg: float = 45.0  # ArduPlane ROLL_LIMIT_DEG: sets the predicted turn radius
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
    time_scale: float = 1.0  # vehicles' clock speed; paces steps only when no looks arrive
    #: the vehicles are ``swarmplan sim --lockstep``: grant simulated time one decision period at
    #: a time (mavlink_bridge/lockstep_clock.py); the run is then repeatable for a seed
    lockstep: bool = False
    command_retry_s: float = 0.3
    command_attempts: int = 5
    #: arm / mode commands of the launch are not time-critical: try them longer over a lossy link
    launch_command_attempts: int = 12
    #: write the planner and loop state here after every step (mavlink_bridge/checkpoint.py)
    checkpoint_path: Path | None = None
    resume: bool = False  # carry on from checkpoint_path instead of starting afresh
    signing_key: bytes | None = None  # MAVLink 2 signing (mavlink_bridge/signing.py)
    tlog_path: Path | None = None
    progress: Callable[[str], None] | None = None
    on_step: Callable[[StepStatus], None] | None = None


@dataclass
class StepStatus:
    """What one decision step did (for a progress display)."""

    step: int
    steps: int
    active: int
    lost: list[int]
    coverage: float
    engaged: int
    engaged_value: float
    overrides: int


@dataclass
class LinkEvent:
    step: int
    uav: int
    event: str  # "lost" or "rejoined"
    wall_s: float


@dataclass
class MissionReport:
    """The result dict (same fields as ``swarmplan run``) and the daemon's own account."""

    result: dict[str, Any]
    events: list[LinkEvent] = field(default_factory=list)


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
            scenario, options.threat_margin_km, options.separation_margin_km
        )
        self.events: list[LinkEvent] = []
        self.tlog: TlogWriter | None = None
        self.link: SwarmLink | None = None
        self.overrides = {
            "area": 0,
            "threat": 0,
            "separation": 0,
            "range": 0,
            "predicted_threat": 0,
            "predicted_separation": 0,
        }
        slowest, fastest = options.airspeed_range_mps or (cfg.speed_mps, 1.5 * cfg.speed_mps)
        if not 0 < slowest <= cfg.speed_mps <= fastest:
            raise UserError(
                f"airspeed range {slowest:g}..{fastest:g} m/s must hold the scenario's speed "
                f"{cfg.speed_mps:g} m/s (--airspeed-range MIN:MAX with MIN <= speed <= MAX)"
            )
        self.plane = PlaneModel(
            speed_mps=cfg.speed_mps,
            bank_limit_deg=options.bank_limit_deg,
            min_speed_mps=slowest,
            max_speed_mps=fastest,
        )
        self.flight_envelope = (
            FlightEnvelope(
                self.envelope,
                self.plane,
                step_s=cfg.step_s,
                horizon_s=options.prediction_horizon_s,
                threat_margin_km=options.predicted_threat_margin_km,
                separation_margin_km=options.predicted_separation_margin_km,
                leg_timing=options.leg_timing,
            )
            if options.prediction_horizon_s > 0
            else None
        )
        self._look_gaps: list[float] = []
        self._last_step_wall = 0.0
        self.refused_commands = 0
        self._target_values = {t.id: t.value for t in scenario.targets}
        self.fingerprint = mission_fingerprint(scenario, options.seed, self.n, self.steps)
        self.checkpoints = (
            None
            if options.checkpoint_path is None
            else CheckpointWriter(options.checkpoint_path, self.fingerprint)
        )
        self.resume_from: Checkpoint | None = None
        self.clock: LockstepClock | None = None

    # ------------------------------------------------------------------ helpers

    def say(self, text: str) -> None:
        if self.options.progress is not None:
            self.options.progress(text)

    def vehicle(self, uav: int) -> VehicleState:
        assert self.link is not None
        return self.link.vehicles[uav + 1]

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
        unanswered then is sent again at the next step."""
        assert self.link is not None
        opts = self.options
        if attempts is None:
            attempts = opts.command_attempts
            if opts.lockstep:
                attempts = max(attempts, math.ceil(opts.lost_after_s / opts.command_retry_s))
        return send_commands(self.link, commands, opts.command_retry_s, attempts, deadline)

    def step_deadline(self) -> float | None:
        """Paced time: the instant (monotonic) by which this step's commands must be out, 60 %
        of a decision period (wall seconds at ``time_scale``) after its looks came in; lockstep:
        none, simulated time waits."""
        if self.clock is not None:
            return None
        period_s = self.scenario.config.step_s / max(self.options.time_scale, 1e-6)
        return time.monotonic() + STEP_DEADLINE_SHARE * period_s

    def note_lateness(self, step: int, looks: dict[int, Look]) -> None:
        """Paced time: is the daemon keeping the vehicles' clock? A step is late when its
        commands go out more than half a decision period (of the vehicles' clock) after its
        decision instant (the newest look), so its targets were planned from positions long
        gone, or when a whole decision instant passed without a decision (the decision instants
        of this step and the last more than 1.5 periods apart: the daemon stalled, and the
        planes flew two legs on one command). Late steps are counted in ``late_steps``; the
        first one is said with what to do about it."""
        if self.clock is not None or not looks:
            return
        step_ms = 1e3 * self.scenario.config.step_s
        instant_ms = max(look.time_boot_ms for look in looks.values())
        behind_ms = max(self.vehicle(i).time_boot_ms - looks[i].time_boot_ms for i in looks)
        previous_ms, self._decision_instant_ms = self._decision_instant_ms, instant_ms
        stalled = previous_ms is not None and instant_ms - previous_ms > 1.5 * step_ms
        if behind_ms <= 0.5 * step_ms and not stalled:
            return
        self.late_steps += 1
        if self.late_steps == 1:
            what = (
                f"{(instant_ms - previous_ms) / 1e3:.0f} s passed between two decisions"
                if stalled
                else f"they had flown {behind_ms / 1e3:.1f} s past the decision instant as its "
                "commands went out"
            )
            self.say(
                f"warning: the daemon is behind the vehicles' clock at step {step}: {what} (a "
                f"step is {step_ms / 1e3:g} s); lower the vehicles' speedup (--time-scale "
                f"{self.options.time_scale:g}) or use lockstep"
            )

    # ------------------------------------------------------------------ phases

    def connect(self) -> SwarmLink:
        if self.options.tlog_path is not None:
            self.tlog = TlogWriter(self.options.tlog_path, append=self.options.resume)
        expected = set(self.system_ids)
        self.link = SwarmLink.open(
            self.options.connect,
            self.tlog,
            accept_system_id=lambda s: s in expected,
            signing_key=self.options.signing_key,
        )
        if self.options.lockstep:
            self.clock = LockstepClock(self.link, self.scenario.config.step_s)
        return self.link

    def wait_sim(self, done: Callable[[], bool], timeout_s: float) -> bool:
        """Pump until ``done()``; against a lockstep simulator grant simulated time meanwhile
        (``timeout_s`` then counts simulated seconds)."""
        assert self.link is not None
        if self.clock is None:
            return self.link.pump_until(done, timeout_s)
        vehicles = [self.vehicle(i) for i in range(self.n)]
        return self.clock.run_until(done, vehicles, timeout_s)

    def discover(self) -> None:
        assert self.link is not None
        self.say(f"listening on {self.link.describe()} for {self.n} vehicles")
        wait_for_vehicles(self.link, self.system_ids, self.options.discovery_timeout_s, self.say)
        self.say(f"all {self.n} vehicles heard; waiting for them to finish initialising")
        wait_until_ready(
            self.link, self.system_ids, self.options.ready_timeout_s, wait=self.wait_sim
        )

    def upload_threats(self) -> None:
        assert self.link is not None
        threats = self.scenario.threats
        lat, lon = local_km_to_geodetic(
            [t.x_km for t in threats], [t.y_km for t in threats], self.scenario.origin
        )
        circles = (
            [
                FenceCircle(float(la), float(lo), t.radius_km * 1000.0)
                for la, lo, t in zip(lat, lon, threats, strict=True)
            ]
            if threats
            else []
        )
        upload_fence(self.link, [self.vehicle(i) for i in range(self.n)], circles)
        self.say(f"fence uploaded: {len(circles)} exclusion circles to each vehicle")

    def arm(self, attempts: int = 3) -> None:
        """Arm every vehicle; a refusal is retried, then reported with the prearm reasons."""
        assert self.link is not None
        todo = [self.vehicle(i) for i in range(self.n) if not self.vehicle(i).armed]
        for attempt in range(attempts):
            started = time.monotonic()
            tries = self.options.launch_command_attempts
            results = self.send([arm_command(v) for v in todo], tries)
            todo = [c.vehicle for c in results if not c.accepted]
            if not todo:
                break
            self.link.pump_until(lambda: False, 0.3)  # let the STATUSTEXTs arrive
            if attempt == attempts - 1:
                cmd = next(c for c in results if not c.accepted)
                reasons = cmd.vehicle.prearm_reasons(since_s=started - 0.5)
                because = "; ".join(reasons) if reasons else "no PreArm message"
                result = result_name(cmd.ack.result) if cmd.ack else "no answer"
                raise CommandRefusedError(
                    f"vehicle {cmd.vehicle.system_id} refused to arm ({result}): {because}"
                )
            self.link.pump_until(lambda: False, 1.0)
        self.say(f"armed {self.n} vehicles")

    def take_off(self) -> None:
        """TAKEOFF mode, wait for the climb, then GUIDED."""
        assert self.link is not None
        vehicles = [self.vehicle(i) for i in range(self.n)]
        climb = min(self.options.takeoff_altitude_m, self.scenario.altitude_m)
        attempts = self.options.launch_command_attempts
        # vehicles already flying (a restarted daemon, airborne SITL) go straight to GUIDED
        self.link.pump_until(lambda: all(v.has_position for v in vehicles), 2.0)
        on_ground = [v for v in vehicles if not (v.armed and v.relative_alt_m >= climb)]
        require_accepted(
            self.send([set_mode_command(v, PLANE_MODE_TAKEOFF) for v in on_ground], attempts)
        )
        if not self.wait_sim(
            lambda: all(v.relative_alt_m >= climb for v in vehicles), self.options.takeoff_timeout_s
        ):
            low = [str(v.system_id) for v in vehicles if v.relative_alt_m < climb]
            raise UserError(
                f"vehicle {', '.join(low)} did not climb to {climb:g} m within "
                f"{self.options.takeoff_timeout_s:g} s of TAKEOFF; check its takeoff setup"
            )
        require_accepted(
            self.send([set_mode_command(v, PLANE_MODE_GUIDED) for v in vehicles], attempts)
        )
        self.say("airborne, GUIDED")

    def return_to_launch(self) -> list[str]:
        """RTL every vehicle still heard; returns one line per vehicle that did not accept."""
        if self.link is None:
            return []
        self.end_leg_timing()  # home at cruise speed
        vehicles = [v for v in self.link.vehicles.values() if not v.lost]
        results = self.send([set_mode_command(v, PLANE_MODE_RTL) for v in vehicles])
        return [c.describe_failure() for c in results if not c.accepted]

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
            heading = self._course_heading(v)
            if heading is None:
                heading = (
                    int(heading_of_angle(math.radians(fallback[i].heading_deg)))
                    if i < len(fallback)
                    else 0
                )
            starts.append(UavStart(float(centre[0]), float(centre[1]), heading * 45.0))
        return tuple(starts)

    @staticmethod
    def _course_heading(v: VehicleState) -> int | None:
        """Heading index of the vehicle's velocity (or compass heading), None if unknown."""
        if math.hypot(v.vn_mps, v.ve_mps) > 1.0:
            return int(heading_of_angle(math.atan2(v.vn_mps, v.ve_mps)))
        if v.heading_cdeg != 65535:
            compass = v.heading_cdeg / 100.0
            return int(heading_of_angle(math.radians(90.0 - compass)))
        return None

    def _update_links(self, step: int) -> None:
        now = time.monotonic()
        for i in range(self.n):
            v = self.vehicle(i)
            silent = v.silent_for(now)
            if not v.lost and silent > self.options.lost_after_s:
                v.lost = True
                self.events.append(LinkEvent(step, i, "lost", now))
                self.say(f"vehicle {v.system_id} lost at step {step} (silent {silent:.1f} s)")
            elif v.lost and silent < min(1.0, self.options.lost_after_s / 2):
                v.lost = False
                self.events.append(LinkEvent(step, i, "rejoined", now))
                self.say(f"vehicle {v.system_id} rejoined at step {step}")

    def _step_gap_s(self) -> float:
        if self._look_gaps:
            return statistics.median(self._look_gaps[-20:])
        return self.scenario.config.step_s / max(self.options.time_scale, 1e-6)

    def wait_for_step(self, step: int, consumed: list[int]) -> dict[int, Look]:
        """Pump until every active vehicle has sent a new look (or a straggler deadline passes).

        Vehicles that send no looks at all (e.g. ArduPlane SITL) are paced by the wall clock:
        one step per ``step_s / time_scale`` seconds."""
        assert self.link is not None
        if self.clock is not None:
            return self._lockstep_step(step, consumed)
        start = time.monotonic()
        first_fresh: float | None = None
        any_looks = any(self.vehicle(i).latest_look >= 0 for i in range(self.n))
        gap = self._step_gap_s()
        limit = max(gap * 3, self.options.lost_after_s + 0.5) if any_looks else gap
        while True:
            self.link.pump(0.003)
            self._update_links(step)
            now = time.monotonic()
            fresh = self._new_looks(consumed)
            if any_looks:
                waiting = [i for i in range(self.n) if i not in fresh and not self.vehicle(i).lost]
                if fresh and first_fresh is None:
                    first_fresh = now
                if fresh and not waiting:
                    break
                if first_fresh is not None and now - first_fresh > max(0.05, 0.4 * gap):
                    break  # stragglers miss this step's look
            elif fresh:
                any_looks = True
                limit = max(gap * 3, self.options.lost_after_s + 0.5)
                continue
            if now - start > limit:
                break
        if self._last_step_wall:
            self._look_gaps.append(time.monotonic() - self._last_step_wall)
        self._last_step_wall = time.monotonic()
        return self._consume(fresh, consumed)

    def _new_looks(self, consumed: list[int]) -> dict[int, Look]:
        """The newest look of every vehicle still heard that sent one since ``consumed``."""
        vehicles = [self.vehicle(i) for i in range(self.n)]
        return {
            i: v.looks[v.latest_look]
            for i, v in enumerate(vehicles)
            if v.latest_look > consumed[i] and not v.lost
        }

    @staticmethod
    def _consume(fresh: dict[int, Look], consumed: list[int]) -> dict[int, Look]:
        for i, look in fresh.items():
            consumed[i] = look.index
        return fresh

    def choose_flight(
        self,
        positions: np.ndarray,
        positions_ms: np.ndarray,
        cells: np.ndarray,
        headings: np.ndarray,
        checked: EnvelopeDecision,
        last_target: list[tuple[float, float] | None],
        flown_km: np.ndarray,
        home_km: np.ndarray,
        active: np.ndarray,
    ) -> FlightChoice:
        """Guided targets whose predicted flight is safe (flight_envelope.py); without the
        flight-path envelope, the aim points of the checked cells. Paths are predicted from each
        plane's latest position, course and speed: in lockstep that is the decision instant
        (``positions``, measured at the vehicle's ``positions_ms``); in paced time the plane has
        flown on while the step was planned."""
        lead = self.options.lead_steps
        speeds = np.full(self.n, self.plane.speed_mps)
        courses = np.empty(self.n)
        decision_positions = positions
        positions = np.array(positions, dtype=float, copy=True)
        elapsed_s = np.zeros(self.n)
        for i in range(self.n):
            v = self.vehicle(i)
            if self.clock is None and v.has_position and active[i]:
                positions[i] = self.local_km(v.lat_deg, v.lon_deg)
                elapsed_s[i] = max(0.0, (v.time_boot_ms - positions_ms[i]) / 1e3)
            if math.hypot(v.vn_mps, v.ve_mps) > 1.0:
                courses[i] = math.atan2(v.vn_mps, v.ve_mps)  # course over ground, from east
                speeds[i] = math.hypot(v.vn_mps, v.ve_mps)
            else:
                courses[i] = int(headings[i]) * math.pi / 4
        if self.flight_envelope is None:
            aims = np.array(
                [
                    self.envelope.aim_point_km(cells[i], checked.next_cells[i], lead)
                    for i in range(self.n)
                ]
            )
            if self.options.leg_timing:
                speeds = leg_speed_mps(
                    self.plane,
                    positions,
                    self.grid.centre_km(cells),
                    self.grid.centre_km(checked.next_cells),
                    speeds,
                    self.scenario.config.step_s,
                )
            else:
                speeds[:] = self.plane.speed_mps
            return FlightChoice(aims, checked.next_cells, checked.next_headings, speeds)
        previous = np.array([t if t is not None else (np.nan, np.nan) for t in last_target])
        choice = self.flight_envelope.choose(
            positions, courses, speeds, cells, headings, checked.next_cells,
            checked.next_headings, previous, flown_km, home_km, active, lead,
            decision_positions, elapsed_s,
        )  # fmt: skip
        for reason, count in choice.overrides.items():
            self.overrides[reason] += count
        return choice

    def speed_commands(self, speeds_mps: np.ndarray, active: np.ndarray) -> list[Command]:
        """DO_CHANGE_SPEED for every active vehicle whose leg airspeed (rounded to 1 m/s)
        differs from the one it last accepted (leg timing only)."""
        if not self.options.leg_timing:
            return []
        wanted = np.round(speeds_mps)
        return [
            change_speed_command(self.vehicle(i), float(wanted[i]))
            for i in range(self.n)
            if active[i] and wanted[i] != self.sent_speeds[i]
        ]

    def speeds_answered(self, commands: list[Command], step: int) -> None:
        """Note accepted airspeeds. A vehicle that refuses one (outside its AIRSPEED_MIN/MAX)
        ends leg timing for the run: every plane is asked back to the scenario's speed."""
        refused = [c for c in commands if c.ack is not None and not c.accepted]
        for cmd in commands:
            if cmd.accepted:
                self.sent_speeds[cmd.vehicle.system_id - 1] = cmd.params[1]
        if not refused:
            return
        self.refused_commands += len(refused)
        self.say(
            f"warning: {refused[0].describe_failure()} (step {step}, {refused[0].params[1]:g} "
            f"m/s); flying every leg at {self.plane.speed_mps:g} m/s from now on (set "
            f"--airspeed-range to the airframe's AIRSPEED_MIN:AIRSPEED_MAX, or --no-leg-timing)"
        )
        self.end_leg_timing()

    def end_leg_timing(self) -> None:
        """Back to the scenario's speed for every vehicle still heard (best effort)."""
        if not self.options.leg_timing or self.link is None:
            return
        self.options = replace(self.options, leg_timing=False)
        if self.flight_envelope is not None:
            self.flight_envelope = replace(self.flight_envelope, leg_timing=False)
        cruise = self.plane.speed_mps
        self.send(
            [change_speed_command(v, cruise) for v in self.link.vehicles.values() if not v.lost]
        )

    def _lockstep_step(self, step: int, consumed: list[int]) -> dict[int, Look]:
        """Lockstep: grant one decision period and wait until every vehicle still heard holds at
        its end; its look of that instant has then arrived (same socket, sent before)."""
        assert self.clock is not None
        vehicles = [self.vehicle(i) for i in range(self.n)]
        self.clock.advance(vehicles, on_pump=lambda: self._update_links(step))
        return self._consume(self._new_looks(consumed), consumed)

    def request_homes(self) -> None:
        """Ask every vehicle whose home is not known yet for HOME_POSITION (REQUEST_MESSAGE):
        the launch point is each UAV's start and return point, and ArduPilot streams it rarely."""
        assert self.link is not None
        missing = [self.vehicle(i) for i in range(self.n) if self.vehicle(i).home is None]
        if missing:
            home = mavlink.MAVLINK_MSG_ID_HOME_POSITION
            self.send([request_message_command(v, home) for v in missing])
            self.link.pump_until(lambda: all(v.home is not None for v in missing), 1.0)

    def release_clock(self) -> None:
        """Lockstep over: let the simulator run on its own (the vehicles fly their RTL)."""
        if self.clock is not None and self.link is not None:
            self.clock.release(list(self.link.vehicles.values()))

    def fly(self) -> MissionReport:
        """Run discovery to RTL and return the result measured over MAVLink."""
        HapfAcoPlanner, MissionRecorder = _import_planner()
        started = time.monotonic()
        if self.options.resume:  # a bad checkpoint fails now, before any vehicle is touched
            if self.options.checkpoint_path is None:
                raise UserError("--resume needs --checkpoint PATH (the file to resume from)")
            self.resume_from = load_for_mission(
                self.options.checkpoint_path, self.fingerprint, HapfAcoPlanner
            )
        if self.link is None:
            self.connect()
        try:
            self.discover()
            self.upload_threats()
            self.arm()
            self.take_off()
            self.request_homes()
            result = self._decision_loop(HapfAcoPlanner, MissionRecorder, started)
        except BaseException:
            failures = self.return_to_launch() if self.link is not None else []
            for line in failures:
                self.say(f"warning: {line}")
            self.release_clock()
            self.close()
            raise
        failures = self.return_to_launch()
        self.release_clock()
        for line in failures:
            self.say(f"warning: {line}")
        self.say("mission over: RTL sent to every vehicle")
        self.close()
        return MissionReport(result, self.events)

    def close(self) -> None:
        if self.link is not None:
            self.link.close()
        if self.tlog is not None:
            self.tlog.close()

    def _decision_loop(self, planner_cls: Any, recorder_cls: Any, started: float) -> dict[str, Any]:
        assert self.link is not None
        scenario, n, cfg = self.scenario, self.n, self.scenario.config
        starts = self.starts_from_telemetry()
        # Real planes stray from cell centres (turn circle ~1 km, 14 s diagonal legs), so the
        # planner itself claims cells with the flight margin on top of d_min; the recorder keeps
        # judging against the scenario's true d_min.
        planning = scenario.with_config(
            min_separation_km=cfg.min_separation_km + self.options.separation_margin_km,
            separation_sense_km=max(
                cfg.separation_sense_km,
                cfg.min_separation_km + 2 * self.options.separation_margin_km,
            ),
        )
        planner = planner_cls(planning, starts, self.options.seed)
        recorder = recorder_cls(
            scenario, starts, turn_tolerance_deg=self.options.turn_tolerance_deg
        )
        home_km = np.array([[s.x_km, s.y_km] for s in starts])
        cells = self.grid.cell_of(home_km)
        headings = np.array([int(heading_of_angle(math.radians(s.heading_deg))) for s in starts])
        commanded_cells, commanded_headings = cells.copy(), headings.copy()
        last_target: list[tuple[float, float] | None] = [None] * n
        consumed = [self.vehicle(i).latest_look for i in range(n)]
        flown_km = np.zeros(n)
        engagements: list[EngagementOutcome | None] = [None] * n
        engage_seq = [0] * n
        pending_engage = [0] * n  # sequence number of an unanswered engagement, asked again
        refusals = [0] * n
        observed = np.zeros(self.grid.shape, dtype=bool)
        engaged_ids: set[int] = set()
        engaged_value = 0.0
        positions = self.grid.centre_km(cells)
        previous_centres = positions.copy()
        # airspeed last accepted by each vehicle (unknown at the start and after a restart)
        self.sent_speeds = np.full(n, np.nan)
        self.looks_missed = 0
        self.late_steps = 0
        self._decision_instant_ms: int | None = None
        positions_ms = np.zeros(n)  # the vehicle's clock when it was at positions[i]
        first_step = 0
        if self.resume_from is not None:  # a restarted daemon: the state after its last step
            loop = resume_loop_state(self, self.resume_from, planner)
            (planner, recorder, starts, home_km, cells, headings, commanded_cells,
             commanded_headings, last_target, consumed, flown_km, engagements, engage_seq,
             pending_engage, refusals, observed, engaged_ids, engaged_value, positions,
             previous_centres) = (loop[name] for name in LOOP_STATE)  # fmt: skip
            first_step = self.resume_from.step + 1
        for step in range(first_step, self.steps + 1):  # the start, then one record per step
            looks = self.wait_for_step(step, consumed) if step > 0 else {}
            deadline = self.step_deadline()
            active = np.array([not self.vehicle(i).lost for i in range(n)])
            reports: list[SensorReport | None] = [None] * n
            for i in range(n):
                v = self.vehicle(i)
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
                if look_km is not None and not stale:
                    positions[i], positions_ms[i] = look_km, look.time_boot_ms
                elif v.has_position:
                    self.looks_missed += step > 0 and look is None
                    positions[i] = self.local_km(v.lat_deg, v.lon_deg)
                    positions_ms[i] = v.time_boot_ms
                cell = self.grid.cell_of(positions[i])
                if look is not None:  # where it looked, which is usually where it is
                    reports[i] = look_report(
                        look, self.grid, scenario.origin, cfg.detection_radius_km,
                        cell=self.grid.cell_of(look_km),
                    )  # fmt: skip
                    observed[reports[i].cells[:, 0], reports[i].cells[:, 1]] = True
                if step == 0:  # where the take-off left it, flying its course
                    course = self._course_heading(v)
                    headings[i] = headings[i] if course is None else course
                else:
                    if np.array_equal(cell, commanded_cells[i]):
                        headings[i] = commanded_headings[i]
                    else:
                        course = self._course_heading(v)
                        headings[i] = commanded_headings[i] if course is None else course
                cells[i] = cell
            decision = planner.step(
                cells.copy(), headings.copy(), reports, engagements, active.copy()
            )
            engagements = [None] * n
            done = np.asarray(decision.done, dtype=bool)
            proposed = np.where(done[:, None], cells, np.asarray(decision.next_cells))
            proposed_h = np.where(done, headings, np.asarray(decision.next_headings))
            checked = self.envelope.check(
                cells, headings, proposed, proposed_h, flown_km, home_km, active
            )
            for o in checked.overrides:
                self.overrides[o.reason] += 1
            flight = self.choose_flight(
                positions, positions_ms, cells, headings, checked, last_target, flown_km,
                home_km, active,
            )  # fmt: skip
            checked.next_cells, checked.next_headings = flight.next_cells, flight.next_headings
            # distance flown so far, between measured cells (as the planner counts)
            centres = self.grid.centre_km(cells)
            if step > 0:
                legs = np.hypot(*(centres - previous_centres).T)
                flown_km[active] += legs[active]
            previous_centres = centres
            recorder.record_step(
                positions.copy(),
                airborne=active.copy(),
                planned_km=self.grid.centre_km(checked.next_cells),
                done=done,
            )
            # one batch: engagement requests first (each vehicle gets its request before its
            # next guided target, so it is resolved where the planner asked for it), then the
            # guided targets and the airspeed of each leg. An engagement left unanswered is
            # asked again with the same sequence number (the camera replays its outcome, never
            # engages twice) before any new one
            requests = [
                (i, engagement_command(self.vehicle(i), pending_engage[i] or engage_seq[i] + 1))
                for i in range(n)
                if active[i] and (bool(decision.engage[i]) or pending_engage[i])
            ]
            for i, cmd in requests:
                engage_seq[i] = max(engage_seq[i], int(cmd.params[3]))
            aims = flight.aims_km
            lat, lon = local_km_to_geodetic(aims[:, 0], aims[:, 1], scenario.origin)
            moves = []
            for i in range(n):
                if not active[i]:
                    continue
                aim = (round(float(aims[i, 0]), 3), round(float(aims[i, 1]), 3))
                if aim == last_target[i] and step % 5:
                    continue  # already flying there (re-sent every 5 steps all the same)
                cmd = reposition_command(
                    self.vehicle(i), float(lat[i]), float(lon[i]), scenario.altitude_m
                )
                moves.append((i, aim, cmd))
            batch = [c for _, c in requests] + [c for *_, c in moves]
            batch += self.speed_commands(flight.speeds_mps, active)
            self.note_lateness(step, looks)
            sent = self.send(batch, deadline=deadline)
            answered, sent = sent[: len(requests)], sent[len(requests) :]
            for i, cmd in zip([r[0] for r in requests], answered, strict=True):
                pending_engage[i] = int(cmd.params[3]) if cmd.ack is None else 0
                if cmd.ack is None:
                    continue  # unanswered: asked again at the next step
                target = int(cmd.ack.result_param2) if cmd.accepted else 0
                value = float(self._target_values.get(target, 0.0)) if target else 0.0
                engagements[i] = EngagementOutcome(target != 0, target, value)
                if target and target not in engaged_ids:
                    engaged_ids.add(target)
                    engaged_value += value
                    recorder.record_engagement(step, i, target, value)
                elif not target:
                    recorder.record_engagement_miss()
            self.speeds_answered(sent[len(moves) :], step)
            for (i, aim, _), cmd in zip(moves, sent[: len(moves)], strict=True):
                if cmd.ack is not None and not cmd.accepted:
                    refusals[i] += 1
                    self.refused_commands += 1
                    self.say(f"warning: {cmd.describe_failure()} (step {step})")
                    if refusals[i] >= self.options.max_refusals:
                        raise CommandRefusedError(
                            f"{cmd.describe_failure()} {refusals[i]} times in a row; check its "
                            f"mode, fence and STATUSTEXT messages"
                        )
                elif cmd.accepted:
                    refusals[i] = 0
                if cmd.accepted:
                    last_target[i] = aim
            commanded_cells = checked.next_cells.copy()
            commanded_headings = checked.next_headings.copy()
            if self.options.on_step is not None:
                self.options.on_step(
                    StepStatus(
                        step,
                        self.steps,
                        int(active.sum()),
                        [i + 1 for i in range(n) if not active[i]],
                        float(observed.mean()),
                        len(engaged_ids),
                        engaged_value,
                        sum(self.overrides.values()),
                    )
                )
            if self.checkpoints is not None:  # atomically, after every step
                here = locals()  # (a comprehension has its own locals() before Python 3.12)
                state = {name: here[name] for name in LOOP_STATE}
                self.checkpoints.save(step, self, state, time.monotonic() - started)
            if done.all():
                break
        extra = {
            "source": "mavlink",
            "endpoints": self.link.describe(),
            "envelope_overrides": dict(self.overrides),
            "refused_commands": self.refused_commands,
            "looks_missed": self.looks_missed,
            "late_steps": self.late_steps,
            "link_events": [
                {"step": e.step, "uav": e.uav, "system_id": e.uav + 1, "event": e.event}
                for e in self.events
            ],
            "lost_uavs": sorted({e.uav for e in self.events if e.event == "lost"}),
            "frames_received": self.link.messages_received,
            "stale_positions": sum(v.stale_positions for v in self.link.vehicles.values()),
            "signing": (
                None if self.link.signature_check is None else self.link.signature_check.counters()
            ),
            "resumed_from_step": None if self.resume_from is None else self.resume_from.step,
            "tlog": str(self.options.tlog_path) if self.options.tlog_path else None,
        }
        return recorder.result(
            self.options.seed, ALGORITHM, time.monotonic() - started, extra=extra
        )


__all__ = ["MissionDaemon", "DaemonOptions", "MissionReport", "StepStatus", "mavlink"]
