"""The simulator: N fixed-wing vehicles over UDP MAVLink in front of one ground-truth world.

One process, one thread, one loop. Each pass of the loop:

1. reads every datagram waiting on any vehicle socket, parses each on its own and dispatches the
   good messages by target system (a frame that reached several vehicle sockets, as a pymavlink
   ``udpin`` sends to every client, is handled once);
2. when a physics tick is due, advances simulated time by exactly ``tick_s`` (kinematics,
   mission progress, fence, range) and, on each decision-period boundary (``step_s`` of the
   scenario), steps the world and reports one sensor look per airborne vehicle;
3. when a telemetry frame is due (wall clock), sends the telemetry streams that are due.

Time: ticks are due at ``tick * tick_s / speedup`` wall seconds after the start (real time is
speedup 1); in fast mode they run back to back; in lockstep mode they run back to back up to the
horizon the ground station granted, and the simulator holds there (``sim_gateway/lockstep.py``).
Simulated time only ever moves in whole ticks and the world draws its randomness only from the
seed, so a run without ground-station input is the same for the same seed whatever the speed,
and commands take effect at tick boundaries (in lockstep, at the hold they were sent in).
"""

from __future__ import annotations

import dataclasses
import math
import selectors
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from mavlink_wire.looks import look_messages
from planner.engagement import EngagementOutcome
from planner.errors import UserError
from planner.geodesy import geodetic_to_local_km, local_km_to_geodetic
from planner.grid import Grid
from planner.scenario import Origin, Scenario
from sim_gateway import flight_modes as modes
from sim_gateway.fixed_wing import FleetKinematics
from sim_gateway.geofence import FleetFence
from sim_gateway.ground_truth import GROUPS, GroundTruthSafety
from sim_gateway.lockstep import Address, ClockMaster, LockstepGate
from sim_gateway.mavlink_endpoint import DatagramParser, LinkStats, VehicleSocket
from sim_gateway.message_handlers import AUTOPILOT_ONLY, HANDLERS
from sim_gateway.mission_protocol import retry_upload
from sim_gateway.signing import enable_signing
from sim_gateway.target_account import TargetAccount
from sim_gateway.telemetry import BUILDERS, FleetSnapshot
from sim_gateway.truth_feed import TruthFeed
from sim_gateway.vehicle import Vehicle
from sim_gateway.world import World

MAX_VEHICLES = 200  # system ids 201-255 are left to ground stations (MAVSDK 245, MAVProxy 255)
TELEMETRY_FRAME_S = 0.02  # telemetry is checked at most 50 times per wall second
#: lockstep: GLOBAL_POSITION_INT of every vehicle once per this many simulated seconds, instead
#: of the wall-clock stream (ticks run back to back, so a wall-clock rate would report a few
#: positions per decision period, at instants that differ from run to run)
LOCKSTEP_POSITION_S = 1.0
DUPLICATE_WINDOW_S = 2.0


class SimulatorError(UserError):
    """The simulator cannot start with these settings; the message says what to change."""


@dataclass(frozen=True)
class SimOptions:
    """How the simulator runs and where its vehicles talk."""

    seed: int = 0
    vehicles: int | None = None  # None: the scenario's UAV count
    speedup: float = 1.0
    fast: bool = False
    tick_s: float = 0.1
    gcs_host: str = "127.0.0.1"
    gcs_port: int = 14550
    per_vehicle_port_base: int | None = None  # vehicle i sends to base + i instead of gcs_port
    bind_host: str = "127.0.0.1"
    bind_port_base: int = 0  # vehicle i binds base + i; 0: any free port
    boot_s: float = 20.0
    airborne: bool = False
    position_rate_hz: float = 10.0
    signing_key: bytes | None = None  # MAVLink 2 signing (sim_gateway/signing.py); None: off
    lockstep: bool = False  # hold at the horizon the ground station grants (SYSTEM_TIME)
    lockstep_timeout_s: float = 10.0  # wall s of ground-station silence that end the lock
    truth_port: int | None = None  # send the true targets to 127.0.0.1:PORT (truth_feed.py)

    def validate(self) -> None:
        if self.fast and self.lockstep:
            raise SimulatorError(
                "--fast and --lockstep exclude each other: lockstep already runs as fast as the "
                "ground station allows; drop one"
            )
        if not (math.isfinite(self.lockstep_timeout_s) and self.lockstep_timeout_s > 0):
            raise SimulatorError(
                f"--lockstep-timeout must be a positive number of seconds, got "
                f"{self.lockstep_timeout_s}"
            )
        if not (math.isfinite(self.speedup) and self.speedup > 0):
            raise SimulatorError(
                f"--speedup must be a positive number, got {self.speedup}; e.g. --speedup 50"
            )
        if not (math.isfinite(self.tick_s) and 0.001 <= self.tick_s <= 1.0):
            raise SimulatorError(
                f"--tick-s must be in [0.001, 1] s, got {self.tick_s}; 0.1 is the default"
            )
        if not (math.isfinite(self.boot_s) and 0 <= self.boot_s <= 600):
            raise SimulatorError(f"--boot-s must be in [0, 600] s, got {self.boot_s}")
        if not (math.isfinite(self.position_rate_hz) and 0 < self.position_rate_hz <= 50):
            raise SimulatorError(f"--telemetry-hz must be in (0, 50], got {self.position_rate_hz}")
        if self.vehicles is not None and not 1 <= self.vehicles <= MAX_VEHICLES:
            raise SimulatorError(f"--vehicles must be in 1..{MAX_VEHICLES}, got {self.vehicles}")
        for name, port, low in (
            ("--gcs-port", self.gcs_port, 1),
            ("--per-vehicle-ports", self.per_vehicle_port_base, 1),
            ("--bind-base-port", self.bind_port_base, 0),
            ("--truth-port", self.truth_port, 1),
        ):
            if port is not None and not low <= port <= 65535:
                raise SimulatorError(f"{name} must be a UDP port in {low}..65535, got {port}")


def resolve_gcs_host(host: str) -> str:
    """The IPv4 address of ``--gcs-host`` (looked up once: the vehicles' ground station is
    bound to it, sim_gateway/lockstep.py)."""
    try:
        return socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_DGRAM)[0][4][0]
    except (OSError, UnicodeError) as exc:
        raise SimulatorError(
            f"--gcs-host {host!r} is not an IPv4 address or a name this machine can resolve "
            f"({exc}); e.g. --gcs-host 127.0.0.1"
        ) from None


def with_vehicle_count(scenario: Scenario, count: int | None) -> Scenario:
    """The scenario with ``count`` UAVs (random starts only: fixed starts fix the count)."""
    if count is None or count == scenario.uav_count:
        return scenario
    if scenario.uav_starts is not None:
        raise SimulatorError(
            f"scenario {scenario.name!r} fixes {scenario.uav_count} UAV starts; drop --vehicles "
            "or use a scenario with random starts"
        )
    return dataclasses.replace(scenario, uav_count=count)


class Simulator:
    """N simulated ArduPlanes and the world they fly in."""

    def __init__(self, scenario: Scenario, options: SimOptions) -> None:
        options.validate()
        scenario = with_vehicle_count(scenario, options.vehicles)
        self.scenario = scenario
        self.options = options
        self.config = scenario.config
        self.origin: Origin = scenario.origin
        self.grid = Grid(self.config.grid_nx, self.config.grid_ny, self.config.cell_km)
        self.world = World(scenario, options.seed)
        self.truth_feed = None if options.truth_port is None else TruthFeed(options.truth_port)
        self.target_account = TargetAccount(self.world)  # ground truth per target (never sent)
        self.stats = LinkStats()
        self.parser = DatagramParser(self.stats)
        self.boot_s = 0.0 if options.airborne else options.boot_s
        self.sim_time_s = 0.0
        self.ticks = 0
        self.decision_step = 0
        self.next_decision_s = self.config.step_s
        self.wall0 = time.monotonic()
        self.utc0_us = int(time.time() * 1e6)
        self.max_range_m = self.config.max_range_km * 1000.0

        starts = scenario.starts_for_seed(options.seed)
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
        gcs_ip = resolve_gcs_host(options.gcs_host)
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
                vehicle = Vehicle(i, self.fleet, self, sock, scenario.altitude_m)
                for name in ("GLOBAL_POSITION_INT", "ATTITUDE"):
                    vehicle.streams.set_rate_hz(name, options.position_rate_hz)
                self.vehicles.append(vehicle)
        except OSError as exc:
            self.close()
            raise SimulatorError(
                f"cannot open UDP socket on {options.bind_host} ({exc.strerror}); choose another "
                "--bind-host / --bind-base-port or stop what holds the port"
            ) from None
        self.sysids = {v.sysid: v for v in self.vehicles}
        self.signature_check = None
        if options.signing_key is not None:
            senders = (c for v in self.vehicles for c in (v.autopilot, v.camera))
            self.signature_check = enable_signing(self.parser, senders, options.signing_key)
        self.selector = selectors.DefaultSelector()
        for sock in self.sockets:
            self.selector.register(sock.sock, selectors.EVENT_READ, sock)
        self.fence_breached = np.zeros(n, dtype=bool)
        self.range_exhausted = np.zeros(n, dtype=bool)
        self.recent_frames: dict[tuple[Address | None, bytes], float] = {}
        self.next_purge_wall = 0.0
        self.next_frame_wall = 0.0
        self.looks_sent = 0
        self.engagements = 0
        self.lockstep = LockstepGate(options.lockstep, options.lockstep_timeout_s)
        self.clock_master = ClockMaster()
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

    def lockstep_grant(
        self, message: mavlink.MAVLink_message, sock: VehicleSocket | None, sender: Address | None
    ) -> None:
        """A SYSTEM_TIME without UTC that arrived on ``sock`` from ``sender``: a lockstep grant
        if it comes from the vehicles' ground station (``ClockMaster``), else dropped."""
        if not self.options.lockstep:
            return  # not a lockstep simulator: a grant means nothing here
        station = None if sock is None else sock.station
        if self.clock_master.admits(message.get_srcSystem(), sender, station, set(self.sysids)):
            self.clock_master.last_heard_wall_s = now = self.wall_s()
            self.lockstep.on_grant(message.time_boot_ms, now)

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
        """Wait up to ``timeout_s`` for datagrams and handle all that arrived; returns how many."""
        handled = 0
        for key, _ in self.selector.select(timeout_s):
            sock: VehicleSocket = key.data
            for data, sender in sock.receive_all():
                self.handle_datagram(data, sock, sender)
                handled += 1
        return handled

    def handle_datagram(
        self, data: bytes, sock: VehicleSocket | None = None, sender: Address | None = None
    ) -> None:
        """One datagram that arrived on ``sock`` from ``sender`` (None: fed in directly)."""
        now = self.wall_s()
        for message in self.parser.parse(data):
            # a frame one sender wrote to several vehicle sockets is handled once; the same
            # bytes from another sender are its own (a copy sent ahead cannot mask the original)
            key = (sender, bytes(message.get_msgbuf()))
            seen = self.recent_frames.get(key)
            if seen is not None and now - seen < DUPLICATE_WINDOW_S:
                self.stats.duplicates += 1
                continue
            self.recent_frames[key] = now
            self.dispatch(message, sock, sender)
        if now >= self.next_purge_wall:
            self.recent_frames = {
                k: t for k, t in self.recent_frames.items() if now - t < DUPLICATE_WINDOW_S
            }
            self.next_purge_wall = now + DUPLICATE_WINDOW_S

    def dispatch(
        self,
        message: mavlink.MAVLink_message,
        sock: VehicleSocket | None = None,
        sender: Address | None = None,
    ) -> None:
        """Hand a good message to the vehicle(s) it is addressed to; a lockstep grant to the
        clock, if it comes from the vehicles' ground station."""
        mtype = message.get_type()
        stats = self.stats
        stats.by_type[mtype] = stats.by_type.get(mtype, 0) + 1
        if mtype == "SYSTEM_TIME" and message.time_unix_usec == 0:
            self.lockstep_grant(message, sock, sender)
            return
        if mtype == "HEARTBEAT" and self.clock_master.is_master(
            message.get_srcSystem(), sender, None if sock is None else sock.station
        ):
            self.clock_master.last_heard_wall_s = self.wall_s()  # keeps the lock (lockstep.py)
        handler = HANDLERS.get(mtype)
        if handler is None or message.get_srcSystem() in self.sysids:
            stats.ignored_messages += 1
            return
        target = getattr(message, "target_system", 0)
        if mtype in AUTOPILOT_ONLY and getattr(message, "target_component", 0) not in (0, 1):
            stats.ignored_messages += 1
            return
        if target == 0:
            targets = self.vehicles
        elif target in self.sysids:
            targets = [self.sysids[target]]
        else:
            stats.ignored_messages += 1
            return
        for vehicle in targets:
            try:
                handler(vehicle, message)
            except (
                ValueError,
                TypeError,
                OverflowError,
                ArithmeticError,
                KeyError,
                IndexError,
                struct.error,
            ):
                # a value no handler expected (NaN where an int goes...): refuse it, keep flying
                stats.rejected_commands += 1

    # ------------------------------------------------------------------ simulating

    def tick(self) -> None:
        """Advance simulated time by one tick."""
        dt = self.options.tick_s
        events = self.fleet.step(dt)
        self.sim_time_s = (self.ticks + 1) * dt
        self.ticks += 1
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
        flying = np.flatnonzero(self.fleet.airborne)
        if flying.size == 0:
            return
        # The look is taken at the position as reported (degE7), so a receiver that converts the
        # reported lat/lon with planner.geodesy finds the very same cell.
        lat, lon = local_km_to_geodetic(
            self.fleet.x_m[flying] / 1000.0, self.fleet.y_m[flying] / 1000.0, self.origin
        )
        lat_e7, lon_e7 = np.rint(lat * 1e7).astype(np.int64), np.rint(lon * 1e7).astype(np.int64)
        x_km, y_km = geodetic_to_local_km(lat_e7 / 1e7, lon_e7 / 1e7, self.origin)
        xy = np.stack([x_km, y_km], axis=1)
        reports = self.world.sense(xy)
        self.target_account.observe(self.decision_step, xy, None, reports, self.time_boot_ms())
        look_cells = self.grid.cell_of(xy)
        boot_ms = self.time_boot_ms()
        utc_us = self.utc0_us + int(self.sim_time_s * 1e6)
        home_amsl = self.home_amsl_m()
        for k, i in enumerate(flying):
            v = self.vehicles[i]
            detected = reports[k].cells[reports[k].detected] - look_cells[k]
            rel_mm = round(float(self.fleet.alt_m[i]) * 1000)
            for message in look_messages(
                ((int(dx), int(dy)) for dx, dy in detected),
                v.look_index,
                boot_ms,
                utc_us,
                int(lat_e7[k]),
                int(lon_e7[k]),
                round(home_amsl * 1000) + rel_mm,
                rel_mm,
            ):
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
        if getattr(self, "selector", None) is not None:
            self.selector.close()
        for sock in self.sockets:
            sock.close()
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
            "datagrams": s.datagrams,
            "frames": s.frames,
            "bad_datagrams": s.bad_datagrams,
            "bad_frames": s.bad_frames,
            "unknown_messages": s.unknown_messages,
            "duplicates": s.duplicates,
            "rejected_commands": s.rejected_commands,
            "ignored_messages": s.ignored_messages,
            "sent": s.sent,
            "stale_commands": s.stale_commands,
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
            "lockstep_grants": self.lockstep.grants,
            "safety": self.truth.summary(),
        }
