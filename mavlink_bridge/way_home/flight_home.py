"""The flight home at the end of a mission, after RTL went out: each plane's way home clear of
the threats (RTL's straight line where it is clear, else guided around them: around_threats.py),
kept d_min from the other planes' ways (a plane circles a safe hold point until its way is
clear: kept_apart.py), and the watch of the flight home, so that it is in the
continuous safety account (return_home.HomeWatch). :class:`FlightHomePhase` does it over a
narrow mission context (:class:`HomeContext`); the daemon's exit path (``finish``) calls its
``return_to_launch`` and, after a completed mission, the watch of the flight home
(home_watch.py); what happened is kept in its :class:`FlightHome`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from mavlink_bridge.safety.safety_envelope import SafetyEnvelope
from mavlink_bridge.vehicles.autopilot_adapter import RTL_COMMANDS, autopilot_for
from mavlink_bridge.vehicles.flight_prediction import PlaneModel
from mavlink_bridge.vehicles.guided_commands import (
    Command,
    change_speed_command,
)
from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_bridge.vehicles.vehicle_loss import link_down
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_bridge.way_home.around_threats import HomeRoutes
from mavlink_bridge.way_home.home_circles import (
    HomeCircles,
    circle_lines,
    home_circle_speeds,
    slow_circle_commands,
)
from mavlink_bridge.way_home.kept_apart import ReturnPlan, ReturnSeparation
from mavlink_bridge.way_home.rtl_at_exit import UNREACHABLE, rtl_line, rtl_recipients
from planner.geodesy import local_km_to_geodetic
from planner.grid import Grid
from planner.scenario import Scenario

#: how long the daemon listens for the return mode of planes sent RTL at the watch's end
#: (vehicle seconds: a few heartbeats)
RTL_SEEN_S = 5.0


@dataclass
class FlightHome:
    """Who flies home how: guided around the threats (``homing``: the waypoint it flies to
    now; ``detoured``: every one that was), holding for another's way home (``holding``: the
    point it circles; ``held``: every one that did; ``unresolved``: no hold cleared its way)."""

    homing: dict[VehicleKey, np.ndarray] = field(default_factory=dict)
    detoured: set[VehicleKey] = field(default_factory=set)
    #: keep the ways home d_min apart: only when the daemon stays to watch the flight home
    separate: bool = False
    holding: dict[VehicleKey, np.ndarray] = field(default_factory=dict)
    #: of ``holding``, the planes that fly through their point on the way home (a detour)
    detouring: set[VehicleKey] = field(default_factory=set)
    held: set[VehicleKey] = field(default_factory=set)
    unresolved: set[VehicleKey] = field(default_factory=set)
    routes: HomeRoutes | None = None  # the way home around threats, for the plane model in force
    #: planes switched to RTL during the mission whose line home crossed a threat, guided out
    #: (``guide_stray_returns``)
    strays: set[VehicleKey] = field(default_factory=set)
    #: who circles home slower than cruise, its home being near another's (``home_circles``)
    circles: HomeCircles = field(default_factory=HomeCircles)
    #: planes a resumed daemon sent home (resume_takeback.py), by system id: why
    sent_home: dict[VehicleKey, str] = field(default_factory=dict)
    #: planes RTL could not reach at the way out (listened for during the watch) ...
    unreached: set[VehicleKey] = field(default_factory=set)
    #: ... and those of them sent home once heard again
    reached_late: set[VehicleKey] = field(default_factory=set)


class HomeOptions(Protocol):
    """The options the flight home reads (``DaemonOptions`` has them)."""

    lost_after_s: float
    leg_timing: bool
    rtl_watch_s: float | None


class HomeContext(Protocol):
    """What the flight home works with (``mission.context.MissionContext`` is one): the
    scenario and grid, the airframe in force and the cell-level envelope (its threat margin),
    the link and, in lockstep, the clock, and the ways to talk to the vehicles."""

    scenario: Scenario
    grid: Grid
    plane: PlaneModel
    envelope: SafetyEnvelope
    link: SwarmLink | None
    clock: object | None  # lockstep: the clock that grants the vehicles' time
    options: HomeOptions

    @property
    def time_scale(self) -> float: ...

    def say(self, text: str) -> None: ...

    def send(
        self, commands: list[Command], attempts: int | None = None, deadline: float | None = None
    ) -> list[Command]: ...

    def wait_sim(self, done: Callable[[], bool], timeout_s: float) -> bool: ...

    def require_link(self) -> SwarmLink: ...

    def vehicles(self) -> list[VehicleState]: ...

    def local_km(self, lat: float, lon: float) -> np.ndarray: ...


class FlightHomePhase:
    """The flight home over one mission's context, with its own state (:class:`FlightHome`):
    RTL at the way out (``return_to_launch``) and its watch (``home_watch.watch_flight_home``),
    and during the mission the planes whose autopilot or a resumed daemon sent home
    (``guide_stray_returns``, ``guide_sent_home``)."""

    def __init__(self, ctx: HomeContext, state: FlightHome | None = None) -> None:
        self.ctx = ctx
        self.state = FlightHome() if state is None else state

    def send_home(self, key: VehicleKey, why: str) -> None:
        """A plane a resumed daemon sends home (``resume_takeback.py``): from now on it flies
        the safe way home (``guide_sent_home``), never the mission."""
        self.state.sent_home[key] = why

    def sent_home(self) -> set[VehicleKey]:
        """The planes a resumed daemon sent home, by system id."""
        return set(self.state.sent_home)

    def result(self, sent_to: list[VehicleKey], skipped: dict[VehicleKey, str]) -> dict[str, Any]:
        """The flight home in the mission's result: RTL sent to (``sent_to`` by
        ``return_to_launch``, and every plane guided or held that got it during the watch),
        guided around threats, held for separation, the home circles' speeds, and why RTL was
        not sent (``skipped``)."""
        flight = self.state
        # a vehicle guided around threats got its RTL during the watch, once the way was clear
        later = (flight.detoured | flight.held) - set(flight.homing) - set(flight.holding)
        later |= flight.reached_late
        return {
            "rtl_sent_to": [k.label() for k in sorted(set(sent_to) | later)],
            "guided_home_around_threats": [k.label() for k in sorted(flight.detoured)],
            "held_for_separation_home": [k.label() for k in sorted(flight.held)],
            "home_circle_speeds_mps": {
                str(k): round(v, 1) for k, v in sorted(flight.circles.speeds_mps.items())
            },
            "rtl_not_sent": {
                str(k): why for k, why in sorted(skipped.items()) if k not in flight.reached_late
            },
        }

    def home_routes(self) -> HomeRoutes:
        """The way home around threats (RTL flies straight) for the plane model and threat
        margin in force (both set from the airframe at launch); the turn onto it with the full
        margin: a plane may fly faster (leg timing) and turn wider than the model (0.25 km let
        an RTL 0.19 km into a threat)."""
        flight = self.state
        env, routes = self.ctx.envelope, flight.routes
        if (
            routes is None
            or routes.plane is not self.ctx.plane
            or routes.margin_km != (env.threat_margin_km)
        ):
            routes = HomeRoutes(
                self.ctx.grid, env.threat_xy_km, env.threat_radius_km, self.ctx.plane,
                margin_km=env.threat_margin_km, turn_margin_km=env.threat_margin_km,
            )  # fmt: skip
            flight.routes = routes
        return routes

    def return_separation(self) -> ReturnSeparation:
        """The flight home kept d_min apart, judged with the way home's threat margin and the
        plane model in force; a plane may stray its loiter radius from its line on the way."""
        routes = self.home_routes()
        return ReturnSeparation(
            routes,
            self.ctx.scenario.config.min_separation_km,
            slack_km=float(self.ctx.plane.loiter_radius_km()),
            speeds_mps=self.state.circles.speeds_mps,
        )

    def home_circles(self) -> HomeCircles:
        """How fast each plane circles its home (``home_circle_speeds``, over every vehicle heard
        with a home that is airborne or lost: a lost plane may be circling its home); says who
        slows down and which homes are too close even then (kept in ``FlightHome.circles``)."""
        heard = self.ctx.link.vehicles.values() if self.ctx.link is not None else []
        homes = {
            v.key: self.ctx.local_km(v.home[0], v.home[1])
            for v in heard
            if v.home is not None and (v.airborne or v.lost)
        }
        d_min = self.ctx.scenario.config.min_separation_km
        circles = home_circle_speeds(homes, self.ctx.plane, d_min)
        self.state.circles = circles
        for line in circle_lines(circles, d_min):
            self.ctx.say(line)
        return circles

    def slow_home_circles(self, sent: list[Command]) -> None:
        """The home circle's airspeed to the planes of ``sent`` that fly home slower than
        cruise (``slow_circle_commands``); says who did not take it."""
        slow = slow_circle_commands(self.state.circles, sent)
        refused = [c.vehicle.key for c in (self.ctx.send(slow) if slow else []) if not c.accepted]
        if refused:
            ids = ", ".join(map(str, refused))
            self.ctx.say(
                f"warning: vehicle(s) {ids} did not take the home circle's "
                "airspeed (DO_CHANGE_SPEED): they circle home at cruise, within d_min of another's "
                "home circle"
            )

    def see_rtl(self, vehicles: list[VehicleState]) -> None:
        """Listen on (the tlog records it) until each of ``vehicles`` reports its autopilot's
        return mode, for at most ``RTL_SEEN_S`` of the vehicles' seconds: a PX4 plane held to
        the watch's end, or every plane of a daemon stopped by SIGTERM, was sent RTL and the
        daemon closed its log on the COMMAND_ACK, before any heartbeat said AUTO.RTL. Not in
        lockstep: the simulator is released next and flies the planes home on its own clock
        (granting time to a simulator that may be gone would hold an exit up)."""
        if not vehicles or self.ctx.clock is not None:
            return

        def returning() -> bool:
            return all(v.lost or autopilot_for(v).returning(v.custom_mode) for v in vehicles)

        self.listen(returning, RTL_SEEN_S)

    def listen(self, done: Callable[[], bool], vehicle_s: float) -> bool:
        """Listen on until ``done`` or for ``vehicle_s`` of the vehicles' seconds (in lockstep:
        granting them); True when ``done``."""
        if self.ctx.clock is not None:
            return self.ctx.wait_sim(done, vehicle_s)
        return self.ctx.require_link().pump_until(done, vehicle_s / self.ctx.time_scale)

    def guide_stray_returns(self) -> list[Command]:
        """During the mission: a plane its autopilot switched to RTL (a fence breach: ArduPlane's
        FENCE_ACTION 1, the simulator's default; a failsafe; a pilot) flies the straight line home,
        through the zone the fence guards when home lies beyond it, and once its heartbeats show
        it out of GUIDED it is lost to the planner (``vehicle_loss.py``) and gets no more targets
        (issue 12: 0.27 km deep at 30 % loss, 20x). Every plane seen in RTL whose way home is not
        clear (``HomeRoutes.rtl_clear``) is guided (DO_REPOSITION, which switches it to GUIDED) to
        the next waypoint of the safe way home, one that gets no deeper into a zone it is in; in
        GUIDED it is (or rejoins) the planner's again at the next step, and the flight envelope
        guides it on. A plane whose line home is clear flies its RTL home. Said once per plane;
        returns the commands to send (one per such plane at each decision step)."""
        routes = self.home_routes()
        commands: list[Command] = []
        for v in self.ctx.vehicles():
            if not (autopilot_for(v).returning(v.custom_mode) and v.armed and v.airborne):
                continue
            if v.key in self.state.sent_home:
                continue  # its flight home is guide_sent_home's
            if v.home is None or not v.has_position or v.link is None or link_down(v) is not None:
                continue
            waypoint = self.way_home(routes, v)[3]
            if waypoint is None:  # RTL's line is clear (or no way is known)
                continue
            if v.key not in self.state.strays:
                self.state.strays.add(v.key)
                self.ctx.say(
                    f"vehicle {v.key} is in RTL during the mission (a fence breach or a "
                    f"failsafe) and its line home crosses a threat: guided out via "
                    f"({waypoint[0]:.1f}, {waypoint[1]:.1f}) km"
                )
            commands.append(self.reposition_to(v, waypoint))
        return commands

    def guide_sent_home(self) -> list[Command]:
        """During the mission: the planes a resumed daemon sent home (``FlightHome.sent_home``) on
        their safe way home, re-judged at every decision step (``homeward_commands``: RTL once the
        straight line is clear, else the next waypoint around the threats, sent when it changes).
        Returns the commands to send."""
        sent = self.state.sent_home
        planes = [
            v
            for v in self.ctx.vehicles()
            if v.key in sent and v.airborne and v.home is not None and link_down(v) is None
        ]
        return self.homeward_commands(planes, announce=False) if planes else []

    def return_to_launch(
        self,
        end_leg_timing: Callable[[list[VehicleState]], object] | None = None,
        separate: bool = False,
    ) -> tuple[list[VehicleKey], dict[VehicleKey, str]]:
        """RTL (at cruise speed) to every airborne vehicle still reachable whose way home is clear
        of threats; one whose is not is guided around them (``homeward_commands``, re-judged by
        ``home_watch.py``). Returns the system ids RTL was sent to and, for every vehicle not
        reachable or not flying, why not; says both, and warns of every vehicle that did not
        accept. ``end_leg_timing``: the decision loop's, once it ran; before it, cruise is asked
        of every plane flying when leg timing is on. ``separate``: keep the ways home d_min
        apart (only when the daemon stays to watch the flight home, ``home_watch.py``)."""
        flight = self.state
        flight.separate = separate
        if self.ctx.link is None:
            return [], {}
        flying, skipped = rtl_recipients(
            self.ctx.link.vehicles.values(), self.ctx.options.lost_after_s
        )
        flight.unreached = {k for k, why in skipped.items() if why.startswith(UNREACHABLE)}
        if end_leg_timing is not None:
            end_leg_timing(flying)  # home at cruise speed
        elif self.ctx.options.leg_timing and flying:
            cruise = self.ctx.plane.speed_mps
            self.ctx.send([change_speed_command(v, cruise) for v in flying])
        # RTL where the way home is clear, else guided around the threats (around_threats.py)
        self.home_circles()
        results = self.ctx.send(self.homeward_commands(flying, announce=True))
        self.slow_home_circles(results)
        for c in results:
            if not c.accepted:
                self.ctx.say(f"warning: {c.describe_failure()}")
        rtl = [c for c in results if c.command in RTL_COMMANDS]
        sent = [c.vehicle.key for c in rtl]
        accepted = [c.vehicle.key for c in rtl if c.accepted]
        line = rtl_line(sent, accepted, skipped)
        if flight.homing:
            around = ", ".join(str(i) for i in sorted(flight.homing))
            line += f"; guided home around the threats: {around}"
        if flight.holding:
            holding = ", ".join(str(i) for i in sorted(flight.holding))
            line += f"; holding for the others' way home: {holding}"
        self.ctx.say(line)
        if not separate:  # no watch follows (an interrupted daemon): see the RTL taken
            self.see_rtl([c.vehicle for c in rtl if c.accepted])
        return sent, skipped

    def homeward_commands(self, vehicles: list[VehicleState], announce: bool) -> list[Command]:
        """Per vehicle: RTL when its way home is clear (``HomeRoutes.rtl_clear``), else a
        DO_REPOSITION to the next safe waypoint (sent again only when the waypoint changes);
        when the daemon stays to watch the flight home, a vehicle whose way would come within
        d_min of another's holds at a safe point until it is clear (``hold_for_separation``)."""
        flight = self.state
        commands: list[Command] = []
        ways: dict[VehicleKey, tuple[np.ndarray, np.ndarray, float, np.ndarray | None]] = {}
        with self.ctx.require_link().keepalive():  # (hundreds of planes: seconds)
            routes = self.home_routes()
            for v in vehicles:
                if v.home is not None and v.has_position:
                    ways[v.key] = self.way_home(routes, v)
            plan = self.hold_for_separation(vehicles, ways) if flight.separate else ReturnPlan()
        holds = plan.holds
        deciding = {v.key for v in vehicles}
        for sid, hold in holds.items():  # a plane in RTL held so that another leaves first
            if sid not in deciding and self.ctx.link is not None and sid in self.ctx.link.vehicles:
                flight.holding[sid] = hold
                commands.append(self.reposition_to(self.ctx.link.vehicles[sid], hold))
        for v in vehicles:
            waypoint = ways[v.key][3] if v.key in ways else None
            was_holding = flight.holding.pop(v.key, None)
            hold = holds.get(v.key)
            if hold is not None:
                flight.holding[v.key] = hold
                flight.homing.pop(v.key, None)
                if was_holding is None or not np.allclose(was_holding, hold):
                    commands.append(self.reposition_to(v, hold))
                continue
            before = flight.homing.get(v.key)
            if waypoint is None:
                flight.homing.pop(v.key, None)
                if was_holding is not None and not announce and v.key not in plan.unresolved:
                    self.ctx.say(f"vehicle {v.key}'s way home is clear: RTL sent")
                if before is not None or was_holding is not None or announce:
                    commands.append(autopilot_for(v).rtl_command(v))
                continue
            flight.homing[v.key] = waypoint
            flight.detoured.add(v.key)
            if before is not None and np.allclose(before, waypoint):
                continue
            if before is None:
                self.ctx.say(
                    f"vehicle {v.key} flies home around the threats (RTL's straight line "
                    f"would cross one): guided via ({waypoint[0]:.1f}, {waypoint[1]:.1f}) km"
                )
            commands.append(self.reposition_to(v, waypoint))
        return commands

    def place_and_home(self, v: VehicleState) -> tuple[np.ndarray, np.ndarray]:
        """Where ``v`` is and its home, in the mission frame (km)."""
        assert v.home is not None
        return self.ctx.local_km(v.lat_deg, v.lon_deg), self.ctx.local_km(v.home[0], v.home[1])

    def way_home(
        self, routes: HomeRoutes, v: VehicleState
    ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray | None]:
        """Where ``v`` is, its home, its course (rad from east), and the next waypoint of its safe
        way home: None when RTL's straight line (and the turn onto it) is clear, or no way is
        known (``HomeRoutes.waypoint``, which judges ``rtl_clear`` first)."""
        xy, home = self.place_and_home(v)
        return xy, home, v.course_rad, routes.waypoint(xy, home, v.course_rad)

    def reposition_to(self, v: VehicleState, xy_km: np.ndarray) -> Command:
        """DO_REPOSITION of ``v`` to ``xy_km`` (mission frame) at the scenario's altitude."""
        lat, lon = local_km_to_geodetic(xy_km[:1], xy_km[1:], self.ctx.scenario.origin)
        altitude_m = self.ctx.scenario.altitude_m
        return autopilot_for(v).reposition_command(v, float(lat[0]), float(lon[0]), altitude_m)

    def hold_for_separation(
        self,
        vehicles: list[VehicleState],
        ways: dict[VehicleKey, tuple[np.ndarray, np.ndarray, float, np.ndarray | None]],
    ) -> ReturnPlan:
        """Which vehicles must hold for another's way home, detour around it, or leave one after
        another, and where (``ReturnSeparation.plan``, returned): every other airborne vehicle
        heard flies RTL home, and may be held again only so that another leaves first; a vehicle
        already holding keeps its point while it is still good. Says who holds or detours, and
        who conflicts with no way found."""
        flight = self.state
        separation = self.return_separation()
        deciding = {v.key for v in vehicles}
        # flights RTL straight home, as the plane model flies them: every other airborne vehicle
        # heard (nobody holds it any more) and the deciding ones whose line home is clear
        rtl: list[tuple[VehicleKey, np.ndarray, np.ndarray, float, float]] = []
        for o in self.ctx.vehicles():
            if o.key in deciding or o.lost or not o.airborne or o.home is None:
                continue
            if o.has_position:
                rtl.append((o.key, *self.place_and_home(o), o.course_rad, o.speed_mps))
        set_count = len(rtl)
        by_id = {v.key: v for v in vehicles}
        for sid, (xy, home, course, waypoint) in ways.items():
            if waypoint is None:
                rtl.append((sid, xy, home, course, by_id[sid].speed_mps))
        flights = {leg.key: leg for leg in separation.flights_home(rtl)}
        set_legs = [flights[w[0]] for w in rtl[:set_count]]
        waiting = []
        for sid, (xy, _home, course, waypoint) in ways.items():
            leg = flights[sid] if waypoint is None else separation.leg(sid, xy, waypoint, False)
            waiting.append((leg, course))
        # planes in RTL may be guided again to let another leave first (``stagger``)
        movable = {w[0]: w[3] for w in rtl[:set_count]}
        plan = separation.plan(
            set_legs, waiting, keep=flight.holding, detouring=flight.detouring, movable=movable
        )
        flight.detouring = set(plan.detours)
        for line in plan.news(flight.holding.keys(), flight.unresolved):
            self.ctx.say(line)
        flight.unresolved |= set(plan.unresolved)
        flight.held |= plan.holds.keys()
        return plan
