"""The launch of a mission, phase by phase: discover, ready, fence, arm, take off, homes.

Each phase is a named unit (:class:`LaunchPhase`) run in order by :func:`run_launch`; a phase
that cannot complete raises a ``UserError`` naming the vehicle and the fix. A new phase (e.g.
reading each airframe's limits before take-off) is one more entry in :func:`launch_phases`, not
an edit of the others. Each phase takes the launch (:class:`Launch`: what it works with and
what it leaves) and talks to the vehicles through the mission context's link and its ``send``
(acknowledged, retried commands) and ``wait_sim`` (pumps; in lockstep it grants simulated time
meanwhile).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from mavlink_bridge.mission.resume_takeback import TakeBack, flying, judge_fleet, send_home
from mavlink_bridge.vehicles.airframe import read_airframes, scenario_warnings
from mavlink_bridge.vehicles.autopilot_adapter import ArduPilot, autopilot_for
from mavlink_bridge.vehicles.discovery import wait_for_vehicles, wait_until_ready
from mavlink_bridge.vehicles.fence_upload import FenceCircle, upload_fence
from mavlink_bridge.vehicles.gcs_failsafe import set_gcs_failsafe
from mavlink_bridge.vehicles.guided_commands import request_message_command, require_accepted
from mavlink_bridge.vehicles.readiness import arm_when_ready
from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_wire.protocol import mavlink
from planner.errors import UserError
from planner.geodesy import local_km_to_geodetic

if TYPE_CHECKING:
    from mavlink_bridge.mission.context import MissionContext
    from mavlink_bridge.results.checkpoint import Checkpoint
    from mavlink_bridge.vehicles.vehicle_loss import LossWatch
    from mavlink_bridge.vehicles.vehicle_state import VehicleState
    from mavlink_bridge.way_home.flight_home import FlightHomePhase


@dataclass
class Launch:
    """What the launch works with and what it leaves: the mission context, the flight home
    (a resumed daemon sends planes home on it), the loss watch (a plane sent home is retired
    from the mission), the checkpoint resumed from (None: a fresh launch), and the take back's
    decision for each plane (``resume_takeback.py``)."""

    ctx: MissionContext
    home: FlightHomePhase
    loss: LossWatch
    resume_from: Checkpoint | None = None
    take_back: list[TakeBack] = field(default_factory=list)


@dataclass(frozen=True)
class LaunchPhase:
    """One phase of the launch: its name (said and listed) and what it does."""

    name: str
    run: Callable[[Launch], None]


def discover(launch: Launch) -> None:
    """A heartbeat of every expected system id (``discovery.wait_for_vehicles``)."""
    ctx = launch.ctx
    link = ctx.require_link()
    ctx.say(f"listening on {link.describe()} for {ctx.n} vehicles")
    wait_for_vehicles(link, ctx.keys, ctx.options.discovery_timeout_s, ctx.say)
    ctx.say(f"all {ctx.n} vehicles heard; waiting for them to finish initialising")


def ready(launch: Launch) -> None:
    """Every autopilot past its initialisation (STANDBY). A resumed daemon does not wait for a
    plane in the air, whatever it reports (a failsafe's CRITICAL): it takes it back
    (``take_back``)."""
    ctx = launch.ctx
    link = ctx.require_link()
    ids = ctx.keys
    if launch.resume_from is not None:
        vehicles = ctx.vehicles()
        link.pump_until(lambda: all(v.has_position for v in vehicles if v.armed), 2.0)
        ids = [v.key for v in vehicles if not flying(v, climb_m(ctx))]
    wait_until_ready(link, ids, ctx.options.ready_timeout_s, wait=ctx.wait_sim)


def fence(launch: Launch) -> None:
    """Every threat zone as a fence exclusion circle, to every vehicle."""
    ctx = launch.ctx
    threats = ctx.scenario.threats
    lat, lon = local_km_to_geodetic(
        [t.x_km for t in threats], [t.y_km for t in threats], ctx.scenario.origin
    )
    circles = (
        [
            FenceCircle(float(la), float(lo), t.radius_km * 1000.0)
            for la, lo, t in zip(lat, lon, threats, strict=True)
        ]
        if threats
        else []
    )
    upload_fence(ctx.require_link(), ctx.vehicles(), circles)
    ctx.say(f"fence uploaded: {len(circles)} exclusion circles to each vehicle")


def failsafe(launch: Launch) -> None:
    """Every vehicle's GCS-loss settings, its autopilot's (``autopilot_adapter.py``): fly on
    to the last guided target (``gcs_failsafe.py``)."""
    ctx = launch.ctx
    vehicles = ctx.vehicles()
    set_gcs_failsafe(ctx.require_link(), vehicles)
    for autopilot in autopilots_of(vehicles):
        ctx.say(f"GCS failsafe set: {autopilot.failsafe_summary()}")


def airframe(launch: Launch) -> None:
    """Each vehicle's flight limits (``airframe.read_airframes``): the plane model of the flight
    prediction and leg timing follows them; a scenario the airframes cannot fly is said now."""
    ctx = launch.ctx
    # the answers are waited for on the wall clock, never by granting a lockstep simulator time:
    # how long they take must not change when the vehicles arm (a seed flies one mission)
    frames = read_airframes(ctx.vehicles(), ctx.scenario.config, ctx.require_link().pump_until)
    ctx.use_airframes(frames)
    for frame in frames:
        ctx.say(f"airframe {frame.describe()}")
    envelope, options = ctx.envelope, ctx.options
    threat = "given" if options.threat_margin_km is not None else "from the airframe"
    apart = "given" if options.separation_margin_km is not None else "from the airframe"
    ctx.say(
        f"safety envelope: legs kept {envelope.threat_margin_km:.2f} km clear of the threat "
        f"zones ({threat}), next cells d_min + {envelope.separation_margin_km:.2f} km apart "
        f"({apart})"
    )
    for line in scenario_warnings(frames, ctx.scenario.config):
        ctx.say(f"warning: {line}")


def arm(launch: Launch) -> None:
    """Arm every vehicle once it is ready to (``readiness.arm_when_ready``: pre-arm checks, GPS
    fix, home), refusals retried within the readiness window, with progress lines. The line
    that ends it says how long it took, and when on the vehicles' own clocks (s since boot)."""
    ctx = launch.ctx
    started = time.monotonic()
    arm_when_ready(
        ctx.vehicles(),
        ctx.options.ready_timeout_s,
        send=lambda commands, tries: ctx.send(commands, tries),
        wait=ctx.wait_sim,
        progress=ctx.say,
        arm_attempts=ctx.options.launch_command_attempts,
        listen=ctx.require_link().pump_until,
    )
    clocks = [v.clock_ms / 1000.0 for v in ctx.vehicles()]
    ctx.say(
        f"armed {ctx.n} vehicles after {time.monotonic() - started:.1f} s (vehicle clocks "
        f"{min(clocks):.1f}..{max(clocks):.1f} s since boot)"
    )


def take_off(launch: Launch) -> None:
    """TAKEOFF mode, then GUIDED for each plane as soon as it has climbed: in TAKEOFF a plane
    flies straight on along its launch heading (ArduPlane until TKOFF_ALT, the simulator too),
    so one kept waiting for a slower one flew on towards whatever lies ahead (at 30 % loss,
    20x, a plane waited 2 s of wall time, 40 s of flight, for another's take-off, and entered
    a threat 4.3 km ahead of its start)."""
    ctx = launch.ctx
    link = ctx.require_link()
    options = ctx.options
    # (a plane a resumed daemon sent home flies home: ``take_back``)
    sent_home = launch.home.sent_home()
    vehicles = [v for v in ctx.vehicles() if v.key not in sent_home]
    climb = climb_m(ctx)
    attempts = options.launch_command_attempts
    if not vehicles:
        return
    # vehicles already flying (a restarted daemon, airborne SITL) go straight to GUIDED
    link.pump_until(lambda: all(v.has_position for v in vehicles), 2.0)
    on_ground = [v for v in vehicles if not flying(v, climb)]
    require_accepted(
        ctx.send([autopilot_for(v).takeoff_command(v, climb) for v in on_ground], attempts)
    )
    guided: set[VehicleKey] = set()
    while len(guided) < len(vehicles):
        if not ctx.wait_sim(
            lambda: any(v.relative_alt_m >= climb for v in vehicles if v.key not in guided),
            options.takeoff_timeout_s,
        ):
            low = [str(v.key) for v in vehicles if v.key not in guided]
            raise UserError(
                f"vehicle {', '.join(low)} did not climb to {climb:g} m within "
                f"{options.takeoff_timeout_s:g} s of TAKEOFF; check its takeoff setup"
            )
        up = [v for v in vehicles if v.key not in guided and v.relative_alt_m >= climb]
        require_accepted(ctx.send([autopilot_for(v).guide_command(v) for v in up], attempts))
        guided.update(v.key for v in up)
    ctx.say(f"airborne, {' / '.join(a.guided_name for a in autopilots_of(vehicles))}")


def autopilots_of(vehicles: list[VehicleState]) -> list[ArduPilot]:
    """The adapters of the vehicles' autopilots, each once, ArduPilot first."""
    return sorted({autopilot_for(v) for v in vehicles}, key=lambda a: a.name)


def climb_m(ctx: MissionContext) -> float:
    """The climb (above home) that ends the TAKEOFF phase; a plane armed and above it is
    flying (``resume_takeback.flying``)."""
    return min(ctx.options.takeoff_altitude_m, ctx.scenario.altitude_m)


def take_back(launch: Launch) -> None:
    """A resumed daemon (nothing at a fresh launch): every plane in the air taken back
    whatever its status and mode, judged from where it is: those that can continue the
    mission go on (GUIDED at take-off, next), the others are sent home; one line per plane
    says which and why (``resume_takeback.py``)."""
    ctx = launch.ctx
    if launch.resume_from is None:
        return
    vehicles = ctx.vehicles()
    ctx.require_link().pump_until(lambda: all(v.has_position for v in vehicles), 2.0)
    request_homes(launch)  # the way home of a plane sent home is judged to its own
    decisions = judge_fleet(ctx, launch.home.home_routes(), launch.resume_from, climb_m(ctx))
    launch.take_back = decisions
    for t in decisions:
        ctx.say(t.line())
    send_home(ctx, launch.home, launch.loss, decisions)


def request_homes(launch: Launch) -> None:
    """Ask every vehicle whose home is not known yet for HOME_POSITION (REQUEST_MESSAGE): the
    launch point is each UAV's start and return point, and ArduPilot streams it rarely."""
    ctx = launch.ctx
    link = ctx.require_link()
    missing = [v for v in ctx.vehicles() if v.home is None]
    if missing:
        home = mavlink.MAVLINK_MSG_ID_HOME_POSITION
        ctx.send([request_message_command(v, home) for v in missing])
        link.pump_until(lambda: all(v.home is not None for v in missing), 1.0)


def launch_phases() -> list[LaunchPhase]:
    """The launch, in order (docs/daemon.md, "A mission, phase by phase")."""
    return [
        LaunchPhase("discover", discover),
        LaunchPhase("ready", ready),
        LaunchPhase("airframe", airframe),
        LaunchPhase("fence", fence),
        LaunchPhase("failsafe", failsafe),
        LaunchPhase("arm", arm),
        LaunchPhase("take back", take_back),
        LaunchPhase("take off", take_off),
        LaunchPhase("homes", request_homes),
    ]


def run_launch(
    launch: Launch,
    phases: list[LaunchPhase],
    enter: Callable[[str], None],
    said: Callable[[], None] = lambda: None,
) -> None:
    """Run ``phases`` in order, telling ``enter`` the name of each as it starts (the daemon
    notes the phase it is in, for its exit report), and ``said`` as each ends, however it
    ends (the daemon says what the link has to say)."""
    for phase in phases:
        enter(phase.name)
        try:
            phase.run(launch)
        finally:
            said()  # e.g. a second address refused while the vehicles were found
