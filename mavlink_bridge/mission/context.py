"""What every phase of a mission works with, and nothing of any phase's own state.

:class:`MissionContext` holds the mission's surroundings: the scenario and the options, the grid
and the expected vehicles (their (link, system id) keys, index = UAV: ``FleetMap``), the link
and, in lockstep, the clock that grants simulated time, the airframe in force (the plane model,
the cell-level and the flight-path envelopes: the scenario's until the airframes are read at
launch), the mission's counters (``MissionAccount``), and the ways to talk to the vehicles:
``send`` (acknowledged, retried commands), ``wait_sim`` (pump; in lockstep grant time meanwhile)
and ``say``. The launch (``launch.py``), the take back after a restart (``resume_takeback.py``),
the decision loop (``decision_step.py``, ``pacing.py``) and the flight home
(``way_home/flight_home.py``) each own their state and take this context."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from mavlink_bridge.mission.lockstep_clock import LockstepClock
from mavlink_bridge.mission.options import DaemonOptions
from mavlink_bridge.mission.pacing import STEP_DEADLINE_SHARE
from mavlink_bridge.results.mission_result import MissionAccount
from mavlink_bridge.safety.flight_envelope import FlightEnvelope
from mavlink_bridge.safety.safety_envelope import SafetyEnvelope
from mavlink_bridge.vehicles.airframe import (
    MAX_SEPARATION_MARGIN_KM,
    MAX_THREAT_MARGIN_KM,
    Airframe,
    fleet_plane_model,
    scenario_plane_model,
    separation_margin_km,
    threat_margin_km,
)
from mavlink_bridge.vehicles.guided_commands import Command, send_commands
from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_bridge.vehicles.vehicle_key import FleetMap, VehicleKey, split_first_uav
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from planner.errors import UserError
from planner.geodesy import geodetic_to_local_km
from planner.grid import Grid
from planner.scenario import Scenario

#: a decision step's commands are sent this many times before its deadline when unanswered
#: (``MissionContext.send``), resent no faster than every ``MIN_RETRY_S`` of wall time
STEP_SENDS = 5
MIN_RETRY_S = 0.02


class MissionContext:
    """The mission's surroundings, shared by its phases (see the module docstring)."""

    def __init__(self, scenario: Scenario, options: DaemonOptions) -> None:
        self.scenario = scenario
        self.options = options
        cfg = scenario.config
        self.grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
        fleet = options.fleet or tuple(range(options.expect or scenario.uav_count))
        self.n = len(fleet)
        if self.n <= 0:
            raise UserError("--expect must be at least 1")
        #: the scenario's UAV of each vehicle flown (index = the daemon's UAV index)
        self.fleet = tuple(fleet)
        #: the endpoints as opened, and the network of each (``--connect SPEC@FIRST``)
        specs = [split_first_uav(spec) for spec in options.connect]
        self.endpoint_specs = [spec for spec, _ in specs]
        self.fleet_map = FleetMap(self.fleet, tuple(first for _, first in specs) or (0,))
        #: the vehicle of each UAV flown (index = the daemon's UAV index)
        self.keys = self.fleet_map.keys()
        self._index_of_key = {key: i for i, key in enumerate(self.keys)}
        self.steps = options.steps or scenario.steps
        self.account = MissionAccount()
        self.link: SwarmLink | None = None
        self.clock: LockstepClock | None = None  # lockstep: grants the vehicles' time
        self.envelope = SafetyEnvelope.for_scenario(
            scenario,
            MAX_THREAT_MARGIN_KM if options.threat_margin_km is None else options.threat_margin_km,
            MAX_SEPARATION_MARGIN_KM
            if options.separation_margin_km is None
            else options.separation_margin_km,
        )
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

    @property
    def time_scale(self) -> float:
        return max(self.options.time_scale, 1e-6)

    def say(self, text: str) -> None:
        if self.options.progress is not None:
            self.options.progress(text)

    def require_link(self) -> SwarmLink:
        assert self.link is not None, "connect() first"
        return self.link

    def vehicle(self, uav: int) -> VehicleState:
        return self.require_link().vehicles[self.keys[uav]]

    def index_of(self, key: VehicleKey) -> int:
        """The daemon's UAV index of the vehicle of ``key`` (one of ``keys``)."""
        return self._index_of_key[key]

    def links(self) -> list[int]:
        """The network of each endpoint, in ``--connect`` order (``SwarmLink``'s ``links``)."""
        return [self.fleet_map.link_of_endpoint(k) for k in range(len(self.endpoint_specs))]

    def vehicles(self) -> list[VehicleState]:
        """The expected vehicles, index = UAV (each heard at least once)."""
        return [self.vehicle(i) for i in range(self.n)]

    def local_km(self, lat: float, lon: float) -> np.ndarray:
        x, y = geodetic_to_local_km(lat, lon, self.scenario.origin)
        return np.array([x[0], y[0]])

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
        if self.options.separation_margin_km is None:
            margin = separation_margin_km(self.plane, self.options.predicted_separation_margin_km)
            self.envelope = replace(self.envelope, separation_margin_km=margin)
        if self.flight_envelope is not None:
            self.flight_envelope = replace(
                self.flight_envelope, model=self.plane, cells=self.envelope
            )
