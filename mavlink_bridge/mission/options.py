"""What a mission run needs besides the scenario: every option of ``swarmplan daemon`` (and of
the daemon that ``swarmplan demo`` runs), with its default."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from mavlink_bridge.results.mission_result import StepListener, StepStatus


@dataclass
class DaemonOptions:
    """Everything a mission run needs besides the scenario."""

    connect: list[str]
    seed: int = 0
    expect: int | None = None  # vehicles expected (system ids 1..N); default: the scenario's UAVs
    #: the scenario's UAVs (0-based) this daemon flies, system ids UAV + 1; None: 0..expect-1.
    #: A planner node (``swarmplan node --uav I``) flies one: (I,)
    fleet: tuple[int, ...] | None = None
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
    #: on top of d_min between the UAVs' next cells (telemetry positions stray from the
    #: cells); None: from the airframe read at launch (``airframe.separation_margin_km``: two
    #: loiter circles plus ``predicted_separation_margin_km``, at most 1 km; 1 km until then,
    #: and for the simulator's 100 m/s plane)
    separation_margin_km: float | None = None
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
    #: who writes (and resumes from) the checkpoint: the daemon, or ``node I`` (swarmplan node)
    checkpoint_role: str = "daemon"
    signing_key: bytes | None = None  # MAVLink 2 signing (mavlink_wire/signing.py)
    #: our MAVLink (system, component) (None: a ground station's, 255/190); a planner node gives
    #: its own, which its autopilot's MAV_GCS_SYSID names (docs/onboard.md)
    source: tuple[int, int] | None = None
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
