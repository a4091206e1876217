"""The simulator: N fixed-wing vehicles over UDP MAVLink in front of one ground-truth world.

One process, one thread, one loop. Each pass of the loop:

1. reads every datagram waiting on any vehicle socket, parses each on its own and dispatches the
   good messages by target system (a frame that reached several vehicle sockets, as a pymavlink
   ``udpin`` sends to every client, is handled once; ``sim_gateway/inbox.py``);
2. when a physics tick is due, advances simulated time by exactly ``tick_s`` (kinematics,
   mission progress, fence, range) and, on each decision-period boundary (``step_s`` of the
   scenario), steps the world and reports one sensor look per airborne vehicle
   (``sim_gateway/sensor_looks.py``);
3. when a telemetry frame is due (wall clock), sends the telemetry streams that are due.

Time: ticks are due at ``tick * tick_s / speedup`` wall seconds after the start (real time is
speedup 1); in fast mode they run back to back; in lockstep mode they run back to back up to the
horizon the ground station granted, and the simulator holds there (``sim_gateway/lockstep.py``).
Simulated time only ever moves in whole ticks and the world draws its randomness only from the
seed, so a run without ground-station input is the same for the same seed whatever the speed,
and commands take effect at tick boundaries (in lockstep, at the hold they were sent in).
Its settings are :class:`~sim_gateway.sim_options.SimOptions`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from planner.engagement import EngagementOutcome
from planner.geodesy import geodetic_to_local_km, local_km_to_geodetic
from planner.grid import Grid
from planner.scenario import Origin, Scenario
from sim_gateway import flight_modes as modes
from sim_gateway.fixed_wing import FleetKinematics
from sim_gateway.geofence import FleetFence
from sim_gateway.ground_truth import GROUPS, GroundTruthSafety
from sim_gateway.inbox import Inbox
from sim_gateway.lockstep import Address, ClockMaster, LockstepGate
from sim_gateway.mavlink_endpoint import LinkStats, VehicleSocket
from sim_gateway.mission_protocol import retry_upload
from sim_gateway.radio import SwarmRadio
from sim_gateway.sensor_looks import Looks
from sim_gateway.signing import enable_signing
from sim_gateway.sim_options import SimOptions, SimulatorError, flown_uavs, resolve_gcs_host
from sim_gateway.target_account import TargetAccount
from sim_gateway.telemetry import BUILDERS
from sim_gateway.telemetry_streams import FleetSnapshot
from sim_gateway.truth_feed import TruthFeed
from sim_gateway.vehicle import Vehicle
from sim_gateway.world import World

TELEMETRY_FRAME_S = 0.02  # telemetry is checked at most 50 times per wall second
#: lockstep: GLOBAL_POSITION_INT of every vehicle once per this many simulated seconds, instead
#: of the wall-clock stream (ticks run back to back, so a wall-clock rate would report a few
#: positions per decision period, at instants that differ from run to run)
LOCKSTEP_POSITION_S = 1.0


class Simulator:
    """N simulated ArduPlanes and the world they fly in."""

    def __init__(self, scenario: Scenario, options: SimOptions) -> None:
        options.validate()
        scenario, uavs = flown_uavs(scenario, options.vehicles, options.first_uav)
        self.scenario = scenario
        self.options = options
        self.config = scenario.config
        self.origin: Origin = scenario.origin
        self.grid = Grid(self.config.grid_nx, self.config.grid_ny, self.config.cell_km)
        self.world = World(scenario, options.seed)
        self.truth_feed = None if options.truth_port is None else TruthFeed(options.truth_port)
        self.target_account = TargetAccount(self.world)  # ground truth per target (never sent)
        self.stats = LinkStats()
        self.boot_s = 0.0 if options.airborne else options.boot_s
        self.sim_time_s = 0.0
        self.ticks = 0
        self.decision_step = 0
        self.next_decision_s = self.config.step_s
        self.utc0_us = int(time.time() * 1e6)
        self.max_range_m = self.config.max_range_km * 1000.0

        starts = scenario.starts_for_seed(options.seed)[uavs.start : uavs.stop]
        n = len(starts)
        self.fleet = FleetKinematics(
            np.array([s.x_km * 1000.0 for s in starts]),
            np.array([s.y_km * 1000.0 for s in starts]),
            # UavStart.heading_deg counts counter-clockwise from east (the grid's headings)
            np.radians(90.0 - np.array([s.heading_deg for s in starts])) % (2 * np.pi),
            airspeed_mps=self.config.speed_mps,
        )
        self.fence = FleetFence(n)
        self.sockets: list[VehicleSocket] = []
        self.vehicles: list[Vehicle] = []
        self._open_vehicles(n, resolve_gcs_host(options.gcs_host))
        self.lockstep = LockstepGate(options.lockstep, options.lockstep_timeout_s)
        self.clock_master = ClockMaster()
        self.inbox = Inbox(self.vehicles, self.stats, self.lockstep, self.clock_master)
        self.radio = SwarmRadio(options.radio, self.sockets, self.fleet, options.seed)
        self.radio.backlog_limit_s = self.config.step_s
        self.inbox.on_swarm_frame = lambda message, sock: self.radio.on_frame(
            message, sock, self.sim_time_s
        )
        if options.radio_ground_port is not None:  # a ground station on the swarm's channel
            width, height = self.config.area_km
            to = (resolve_gcs_host(options.gcs_host), options.radio_ground_port)
            at_km = options.radio_ground_km or (width / 2.0, height / 2.0)
            try:
                self.radio.listen_on_ground(options.bind_host, to, at_km)
            except SimulatorError:
                self.close()
                raise
        self.signature_check = None
        if options.signing_key is not None:
            senders = (c for v in self.vehicles for c in (v.autopilot, v.camera))
            self.signature_check = enable_signing(self.inbox.parser, senders, options.signing_key)
        self.fence_breached = np.zeros(n, dtype=bool)
        self.range_exhausted = np.zeros(n, dtype=bool)
        self.next_frame_wall = 0.0
        self.looks_sent = 0
        self.engagements = 0
        self.fence_breaches = 0
        self.truth = GroundTruthSafety(
            n,
            np.array([[t.x_km, t.y_km] for t in scenario.threats], float).reshape(-1, 2) * 1e3,
            np.array([t.radius_km for t in scenario.threats], float) * 1e3,
            self.config.min_separation_km * 1e3,
        )
        self._group_index = {name: k for k, name in enumerate(GROUPS)}
        self._home_cache: tuple[tuple[float, ...], list[int], list[int]] | None = None
        if options.airborne:
            self._start_airborne()

    def _open_vehicles(self, n: int, gcs_ip: str) -> None:
        """One UDP socket and one :class:`Vehicle` per row of the fleet, each sending to its
        ground-station port (``--gcs-port`` or ``--per-vehicle-ports``)."""
        options = self.options
        try:
            for i in range(n):
                port = (
                    options.gcs_port
                    if options.per_vehicle_port_base is None
                    else options.per_vehicle_port_base + i
                )
                bind_port = options.bind_port_base + i if options.bind_port_base else 0
                sock = VehicleSocket(options.bind_host, bind_port, (gcs_ip, port), self.stats)
                self.sockets.append(sock)
                vehicle = Vehicle(i, self.fleet, self, sock, self.scenario.altitude_m)
                for name in ("GLOBAL_POSITION_INT", "ATTITUDE"):
                    vehicle.streams.set_rate_hz(name, options.position_rate_hz)
                self.vehicles.append(vehicle)
        except OSError as exc:
            self.close()
            raise SimulatorError(
                f"cannot open UDP socket on {options.bind_host} ({exc.strerror}); choose another "
                "--bind-host / --bind-base-port or stop what holds the port"
            ) from None

    # ------------------------------------------------------------------ host services

    def wall_s(self) -> float:
        return time.monotonic()

    def home_amsl_m(self) -> float:
        return self.origin.alt_m

    def local_to_geodetic(self, x_m: float, y_m: float) -> tuple[float, float]:
        lat, lon = local_km_to_geodetic(x_m / 1000.0, y_m / 1000.0, self.origin)
        return float(lat[0]), float(lon[0])

    def geodetic_to_local(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        x, y = geodetic_to_local_km(lat_deg, lon_deg, self.origin)
        return float(x[0]) * 1000.0, float(y[0]) * 1000.0

    def set_fence(self, index: int, circles: np.ndarray) -> None:
        self.fence.set_circles(index, circles)

    def fence_circles(self, index: int) -> np.ndarray:
        return self.fence.per_vehicle[index]

    def engage(self, index: int) -> EngagementOutcome:
        xy_km = np.array([self.fleet.x_m[index], self.fleet.y_m[index]]) / 1000.0
        self.engagements += 1
        outcome = self.world.engage(xy_km, self.decision_step)
        self.target_account.record_engagement(self.decision_step, index, outcome)
        return outcome

    def snapshot(self) -> FleetSnapshot:
        """Geodetic positions of every vehicle (one vectorised conversion) and clocks."""
        lat, lon = local_km_to_geodetic(
            self.fleet.x_m / 1000.0, self.fleet.y_m / 1000.0, self.origin
        )
        homes = tuple(c for v in self.vehicles for c in (v.home_x_m, v.home_y_m))
        if self._home_cache is None or self._home_cache[0] != homes:
            hx = np.array(homes[0::2]) / 1000.0
            hy = np.array(homes[1::2]) / 1000.0
            hlat, hlon = local_km_to_geodetic(hx, hy, self.origin)
            self._home_cache = (
                homes,
                np.rint(hlat * 1e7).astype(int).tolist(),
                np.rint(hlon * 1e7).astype(int).tolist(),
            )
        if np.isfinite(self.max_range_m):
            left = 1.0 - self.fleet.distance_flown_m / self.max_range_m
            pct = np.clip(np.rint(left * 100), 0, 100).astype(int).tolist()
        else:
            pct = [100] * self.fleet.n
        return FleetSnapshot(
            np.rint(lat * 1e7).astype(int).tolist(),
            np.rint(lon * 1e7).astype(int).tolist(),
            self._home_cache[1],
            self._home_cache[2],
            self.time_boot_ms(),
            self.utc0_us + int(self.sim_time_s * 1e6),
            pct,
        )

    def time_boot_ms(self) -> int:
        return int(round(self.sim_time_s * 1000))

    # ------------------------------------------------------------------ setup

    def _start_airborne(self) -> None:
        """--airborne: every vehicle starts armed, flying at the scenario altitude, in LOITER."""
        self.fleet.airborne[:] = True
        self.fleet.alt_m[:] = self.scenario.altitude_m
        self.fleet.target_alt_m[:] = self.scenario.altitude_m
        for v in self.vehicles:
            v.armed = True
            v.set_mode(modes.LOITER)

    # ------------------------------------------------------------------ receiving

    def poll(self, timeout_s: float) -> int:
        """Wait up to ``timeout_s`` for datagrams and handle all that arrived; returns how many
        (:meth:`Inbox.poll <sim_gateway.inbox.Inbox.poll>`)."""
        return self.inbox.poll(timeout_s)

    def handle_datagram(
        self, data: bytes, sock: VehicleSocket | None = None, sender: Address | None = None
    ) -> None:
        """One datagram that arrived on ``sock`` from ``sender`` (None: fed in directly)."""
        self.inbox.handle_datagram(data, sock, sender)

    # ------------------------------------------------------------------ simulating

    def tick(self) -> None:
        """Advance simulated time by one tick."""
        dt = self.options.tick_s
        events = self.fleet.step(dt)
        self.sim_time_s = (self.ticks + 1) * dt
        self.ticks += 1
        self.radio.deliver_due(self.sim_time_s)
        for i in np.flatnonzero(events.arrived):
            self.vehicles[i].on_arrived()
        for i in np.flatnonzero(events.climbed):
            self.vehicles[i].on_climbed()
        for v in self.vehicles:
            if v.item_wait_until_s is not None:
                v.on_timer()
        self._check_fence()
        self._check_range()
        self.truth.observe(
            self.sim_time_s, self.fleet.x_m, self.fleet.y_m, self.fleet.airborne, self._groups()
        )
        if self.sim_time_s + 1e-9 >= self.next_decision_s:
            self.next_decision_s += self.config.step_s
            self.decision()
        if self.lockstep.locked:
            every = max(1, round(LOCKSTEP_POSITION_S / dt))
            # not at the horizon: there the hold marker reports the position, after the
            # HEARTBEAT of that instant (a position stamped with the horizon tells the ground
            # station the vehicle holds, so its state at the horizon must already be out)
            at_horizon = not self.lockstep.allows((self.ticks + 1) * dt)
            if self.ticks % every == 0 and not at_horizon:
                snapshot = self.snapshot()
                for v in self.vehicles:
                    v.send(BUILDERS["GLOBAL_POSITION_INT"](v, snapshot))

    def _groups(self) -> list[int]:
        """Each vehicle's ground-truth mode group (``ground_truth.GROUPS``)."""
        index = self._group_index
        out = []
        for v in self.vehicles:
            if v.mode == modes.RTL:  # a GCS failsafe changes nothing in RTL (failsafe.py)
                out.append(index["rtl"])
            elif v.failsafe.stage:
                out.append(index["failsafe"])
            elif v.mode == modes.GUIDED:
                out.append(index["guided"])
            else:
                out.append(index["other"])
        return out

    def _check_fence(self) -> None:
        inside = self.fence.inside(self.fleet.x_m, self.fleet.y_m) & self.fleet.airborne
        for i in np.flatnonzero(inside & ~self.fence_breached):
            self.fence_breaches += 1
            self.vehicles[i].on_fence_breach()
        for i in np.flatnonzero(~inside & self.fence_breached):
            self.vehicles[i].on_fence_clear()
        self.fence_breached = inside

    def _check_range(self) -> None:
        if not np.isfinite(self.max_range_m):
            return
        out = self.fleet.distance_flown_m >= self.max_range_m
        for i in np.flatnonzero(out & ~self.range_exhausted):
            self.vehicles[i].on_range_exhausted()
        self.range_exhausted = out

    def decision(self) -> None:
        """One decision period: the world moves, every airborne vehicle takes one look."""
        self.world.step(self.config.step_s)
        self.decision_step += 1
        if self.truth_feed is not None:
            self.truth_feed.send(self.world, self.decision_step)
        if not self.fleet.airborne.any():
            return
        looks = Looks.take(self.world, self.grid, self.origin, self.fleet)
        self.target_account.observe(
            self.decision_step, looks.xy_km, None, looks.reports, self.time_boot_ms()
        )
        boot_ms = self.time_boot_ms()
        utc_us = self.utc0_us + int(self.sim_time_s * 1e6)
        home_amsl = self.home_amsl_m()
        for k, i in enumerate(looks.flying):
            v = self.vehicles[i]
            altitude = float(self.fleet.alt_m[i])
            for message in looks.messages(k, v.look_index, boot_ms, utc_us, home_amsl, altitude):
                v.send_from_camera(message)
            v.look_index += 1
            self.looks_sent += 1

    # ------------------------------------------------------------------ telemetry

    def telemetry_frame(self, now_wall: float) -> None:
        """Send every stream that is due, check link failsafes and stalled uploads."""
        snapshot = None
        gate = self.lockstep
        ticking = gate.locked and gate.held_at_s != gate.horizon_s
        for v in self.vehicles:
            due = v.streams.due(now_wall)
            if ticking and "GLOBAL_POSITION_INT" in due:
                # lockstep on the way to a horizon: positions go by simulated time (tick), so
                # the same seed gives the same reports; a wall-clock one would land at a
                # different instant each run (while held, every report is of the held instant)
                due.remove("GLOBAL_POSITION_INT")
            if due:
                if snapshot is None:
                    snapshot = self.snapshot()
                for name in due:
                    v.send(BUILDERS[name](v, snapshot))
            if not gate.locked:  # in lockstep the ground station is the clock (failsafe.py)
                v.check_failsafe(now_wall)
            if v.missions.upload is not None:
                retry_upload(v, now_wall)

    # ------------------------------------------------------------------ running

    def run(
        self,
        sim_duration_s: float | None = None,
        stop: threading.Event | None = None,
        wall_limit_s: float | None = None,
        on_progress: Callable[[Simulator], None] | None = None,
        progress_every_wall_s: float = 5.0,
    ) -> None:
        """Run for ``sim_duration_s`` more simulated s, until ``stop`` is set or the wall limit."""
        opts = self.options
        start_ticks = self.ticks
        end_ticks = (
            None
            if sim_duration_s is None
            else start_ticks + int(round(sim_duration_s / opts.tick_s))
        )
        wall_start = time.monotonic()
        tick_wall = opts.tick_s / opts.speedup
        next_progress = wall_start + progress_every_wall_s
        pace_wall, pace_ticks = wall_start, start_ticks  # where real-time pacing counts from
        while True:
            if end_ticks is not None and self.ticks >= end_ticks:
                break
            if stop is not None and stop.is_set():
                break
            now = time.monotonic()
            if wall_limit_s is not None and now - wall_start >= wall_limit_s:
                break
            if self.lockstep.locked:
                if not self._lockstep_pass(now):
                    pace_wall, pace_ticks = time.monotonic(), self.ticks  # released: pace anew
            elif opts.fast:
                self.poll(0.0)
                self.tick()
            else:
                due = pace_wall + (self.ticks - pace_ticks + 1) * tick_wall
                wait = due - now
                if wait > 0:
                    self.poll(min(wait, TELEMETRY_FRAME_S))
                else:
                    self.poll(0.0)
                    self.tick()
            now = time.monotonic()
            if now >= self.next_frame_wall:
                self.next_frame_wall = now + TELEMETRY_FRAME_S
                self.telemetry_frame(now)
            if on_progress is not None and now >= next_progress:
                next_progress = now + progress_every_wall_s
                on_progress(self)

    def _lockstep_pass(self, now: float) -> bool:
        """One pass of the loop in lockstep mode: tick if granted, else hold (and tell the
        ground station once per horizon). Returns False once the lock is released."""
        gate = self.lockstep
        if gate.allows((self.ticks + 1) * self.options.tick_s):
            self.poll(0.0)
            self.tick()
            return True
        if gate.held_at_s != gate.horizon_s:
            gate.held_at_s = gate.horizon_s
            self.send_hold_marker()
        self.poll(TELEMETRY_FRAME_S)
        if gate.locked and gate.allows((self.ticks + 1) * self.options.tick_s):
            # a new grant: read whatever else the ground station sent before it, so every
            # command of this hold takes effect at this very tick, whatever the socket order
            for _ in range(8):
                if not self.poll(0.0):
                    break
        if gate.timed_out(time.monotonic(), self.clock_master.last_heard_wall_s):
            print(
                f"sim: lockstep released at t={self.sim_time_s:.1f}s: no grant or heartbeat from "
                f"the ground station for {gate.timeout_wall_s:g} s; running at "
                f"{self.options.speedup:g}x",
                flush=True,
            )
        return gate.locked

    def send_hold_marker(self) -> None:
        """Lockstep hold: every vehicle sends its state at the held time, after anything it
        sent for this instant (the sensor look of a decision boundary): SYS_STATUS and
        GPS_RAW_INT (what a ground station's arming readiness reads), HEARTBEAT, then
        GLOBAL_POSITION_INT. The state a ground station acts on at a hold is then that of the
        held instant whatever the wall clock did: without the first two, whether a pre-arm
        verdict that changed at the horizon was in before the next grant depended on the
        once-a-second telemetry's wall timing, and the same seed armed 10-30 s apart."""
        snapshot = self.snapshot()
        for v in self.vehicles:
            for name in ("SYS_STATUS", "GPS_RAW_INT", "HEARTBEAT"):
                v.send(BUILDERS[name](v, snapshot))
            v.send(BUILDERS["GLOBAL_POSITION_INT"](v, snapshot))

    def close(self) -> None:
        if getattr(self, "inbox", None) is not None:
            self.inbox.close()
        for sock in self.sockets:
            sock.close()
        if getattr(self, "radio", None) is not None:
            self.radio.close()
        if getattr(self, "truth_feed", None) is not None:
            self.truth_feed.close()

    def __enter__(self) -> Simulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def summary(self) -> dict[str, object]:
        """Counters of the run so far (for the command line and tests)."""
        s = self.stats
        return {
            "sim_time_s": round(self.sim_time_s, 3),
            "decision_steps": self.decision_step,
            "looks_sent": self.looks_sent,
            "engagements": self.engagements,
            "targets_left": int(self.world.alive.sum()),
            "airborne": int(self.fleet.airborne.sum()),
            **s.counts(),
            "foreign_grants": self.clock_master.refused,
            **(
                {}
                if self.signature_check is None
                else {
                    "unsigned_refused": self.signature_check.unsigned_refused,
                    "bad_signatures": self.signature_check.bad_signatures,
                    "replays_refused": self.signature_check.replays,
                }
            ),
            "fence_breaches": self.fence_breaches,
            "radio": self.radio.summary(),
            "lockstep_grants": self.lockstep.grants,
            "safety": self.truth.summary(),
        }
