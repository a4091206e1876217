"""The planes' telemetry radio between real autopilots (``swarmplan radio-relay``;
docs/onboard.md, "On a companion computer").

Each plane's planner node sits on a spare serial port of its autopilot (SERIAL2: a companion
computer's place); the autopilot forwards the node's swarm-link frames (TUNNEL of the swarm
payload type, target 0/0) to its other MAVLink ports, the telemetry radio's among them. The
relay connects to each autopilot's telemetry port (SERIAL0 of ArduPilot SITL) and stands in for
the radios: a swarm-link frame heard from plane i is written, byte for byte (signature
included), into the telemetry port of every other plane j that the radio model lets hear it
(``sim_gateway.radio.SwarmRadio``, the very model of ``swarmplan sim``: range in km between the
planes, loss per receiver, optional latency and shared bandwidth, counted); plane j's autopilot
forwards it to its own node.

The planes' positions are their own reports on that port: GLOBAL_POSITION_INT of the autopilot
(component 1) heard there, in a local frame around the first position heard (altitude
included). A plane not located yet hears nothing and is heard by no one (counted lost to range).

**Only swarm-link frames are relayed.** A real radio would carry everything, but the relay
carries no HEARTBEAT, command or telemetry of another plane or node (each is counted in
``not_relayed`` by message type): another plane's node heartbeat reaching this autopilot would
count as its ground station (ArduPlane's GCS failsafe listens to HEARTBEATs from
``MAV_GCS_SYSID``), and another plane's telemetry would make this autopilot route its replies
over the radio. The relay's own HEARTBEAT, once a second on every port, is what makes ArduPilot
forward broadcast frames to that port at all (it forwards to the links it has heard MAVLink
on); it comes from system :data:`RELAY_SYSTEM_ID`, component 68 (a telemetry radio), type
generic: never a ground station's identity, so it keeps no plane's failsafe quiet.
"""

from __future__ import annotations

import math
import select
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from mavlink_wire.links import Address, Endpoint, EndpointError, TcpEndpoint, parse_endpoint
from mavlink_wire.protocol import AUTOPILOT_COMPONENT_ID, component_heartbeat, mavlink
from planner.geodesy import geodetic_to_local_km
from planner.scenario import Origin
from sim_gateway.radio import SwarmRadio, is_swarm_frame
from sim_gateway.sim_options import RadioOptions

#: the relay's own MAVLink identity (a SiK radio's system id, MAV_COMP_ID_TELEMETRY_RADIO):
#: never a ground station's, so its heartbeat cannot stand in for one
RELAY_SYSTEM_ID = 51
RELAY_COMPONENT_ID = mavlink.MAV_COMP_ID_TELEMETRY_RADIO
HEARTBEAT_PERIOD_S = 1.0
RECONNECT_S = 0.5
#: a plane at least this far above its home (mm) counts in the separation between planes
AIRBORNE_MM = 10_000


@dataclass
class RelayedPlane:
    """One autopilot's telemetry port and what the relay knows of the plane on it."""

    index: int
    endpoint: Endpoint
    connected: bool = False
    system_id: int | None = None  # the autopilot heard on this port (its first HEARTBEAT)
    address: Address | None = None  # where a udpin peer was heard
    lat_deg: float = math.nan
    lon_deg: float = math.nan
    alt_m: float = math.nan
    airborne: bool = False  # at least AIRBORNE_MM above home
    heartbeat_s: float = -1e9
    next_try_s: float = 0.0
    mav: mavlink.MAVLink = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.mav = mavlink.MAVLink(None, RELAY_SYSTEM_ID, RELAY_COMPONENT_ID)

    def send(self, frame: bytes) -> None:
        """Write ``frame`` into this plane's port (nothing while it is not connected)."""
        if self.connected:
            self.endpoint.send_to(frame, self.address or self.endpoint.default_address())

    @property
    def located(self) -> bool:
        return math.isfinite(self.lat_deg)


class PlanePositions:
    """The planes' positions as the radio reads them (``x_m``, ``y_m``, ``alt_m``; NaN: not
    located), in a local frame around the first position heard."""

    def __init__(self, planes: list[RelayedPlane]) -> None:
        self.planes = planes
        self.origin: Origin | None = None

    def _xy_m(self) -> tuple[np.ndarray, np.ndarray]:
        x = np.full(len(self.planes), np.nan)
        y = np.full(len(self.planes), np.nan)
        for k, p in enumerate(self.planes):
            if p.located and self.origin is None:
                self.origin = Origin(p.lat_deg, p.lon_deg, 0.0)
            if p.located:
                xk, yk = geodetic_to_local_km(p.lat_deg, p.lon_deg, self.origin)
                x[k], y[k] = 1000.0 * xk[0], 1000.0 * yk[0]
        return x, y

    @property
    def x_m(self) -> np.ndarray:
        return self._xy_m()[0]

    @property
    def y_m(self) -> np.ndarray:
        return self._xy_m()[1]

    @property
    def alt_m(self) -> np.ndarray:
        return np.array([p.alt_m for p in self.planes])


class RadioRelay:
    """The radio between the telemetry ports ``specs`` (one per plane, any endpoint the daemon
    accepts; TCP ones are retried until their server is up, and reconnected)."""

    def __init__(self, specs: list[str], options: RadioOptions, seed: int) -> None:
        self.planes = [RelayedPlane(k, parse_endpoint(spec)) for k, spec in enumerate(specs)]
        self.radio = SwarmRadio(options, self.planes, PlanePositions(self.planes), seed)
        self.not_relayed: Counter[str] = Counter()
        self.min_separation_km = math.inf
        self.started_s = time.monotonic()

    # ------------------------------------------------------------------ connections

    def _connect(self, plane: RelayedPlane, now: float) -> None:
        if plane.connected or now < plane.next_try_s:
            return
        if isinstance(plane.endpoint, TcpEndpoint):
            plane.endpoint.connect_timeout_s = 0.5
        try:
            plane.endpoint.open()
        except EndpointError:
            plane.next_try_s = now + RECONNECT_S
            return
        plane.endpoint.closed_reason = None
        plane.connected = True
        plane.heartbeat_s = -1e9

    def _lost(self, plane: RelayedPlane) -> None:
        plane.endpoint.close()
        plane.endpoint = parse_endpoint(plane.endpoint.spec)  # a new stream, a fresh parser
        plane.connected = False
        plane.next_try_s = time.monotonic() + RECONNECT_S

    def close(self) -> None:
        for plane in self.planes:
            plane.endpoint.close()
            plane.connected = False

    def __enter__(self) -> RadioRelay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the loop

    def poll(self, timeout_s: float = 0.05) -> None:
        """Connect what is not connected, say the relay's heartbeat where due, relay what
        arrives within ``timeout_s`` and pass on the frames due (latency)."""
        now = time.monotonic()
        for plane in self.planes:
            self._connect(plane, now)
            if plane.connected and now - plane.heartbeat_s >= HEARTBEAT_PERIOD_S:
                plane.heartbeat_s = now
                plane.send(component_heartbeat(plane.mav, mavlink.MAV_TYPE_GENERIC))
        live = {p.endpoint.fileno(): p for p in self.planes if p.connected}
        ready = select.select(list(live), [], [], timeout_s)[0] if live else time.sleep(timeout_s)
        for fd in ready or ():
            plane = live[fd]
            for msg, address in plane.endpoint.receive():
                self._handle(plane, msg, address)
            if plane.endpoint.closed_reason is not None:
                self._lost(plane)
        self.radio.deliver_due(time.monotonic() - self.started_s)

    def run(self, until) -> None:
        while not until():
            self.poll()

    def _handle(
        self, plane: RelayedPlane, msg: mavlink.MAVLink_message, address: Address | None
    ) -> None:
        if address is not None:
            plane.address = address
        kind = msg.get_type()
        if is_swarm_frame(msg):
            self.radio.on_frame(msg, plane, time.monotonic() - self.started_s)
            return
        from_autopilot = msg.get_srcComponent() == AUTOPILOT_COMPONENT_ID
        if kind == "HEARTBEAT" and from_autopilot and plane.system_id is None:
            plane.system_id = msg.get_srcSystem()  # (the plane is the autopilot on its port)
        if (
            kind == "GLOBAL_POSITION_INT"
            and from_autopilot
            and msg.get_srcSystem() == plane.system_id
            and (msg.lat or msg.lon)
        ):
            plane.lat_deg, plane.lon_deg = msg.lat / 1e7, msg.lon / 1e7
            plane.alt_m = msg.alt / 1000.0
            plane.airborne = msg.relative_alt >= AIRBORNE_MM
            self._separation(plane)
        self.not_relayed[kind] += 1

    def _separation(self, moved: RelayedPlane) -> None:
        """The smallest horizontal distance between ``moved`` and the other airborne planes,
        as their latest reports put them (what really flew, as far as the radio knows)."""
        if not moved.airborne:
            return
        positions = self.radio.fleet
        x, y = positions.x_m, positions.y_m
        gaps = np.hypot(x - x[moved.index], y - y[moved.index]) / 1000.0
        gaps[[not p.airborne or p is moved for p in self.planes]] = np.nan
        if np.isfinite(gaps).any():
            self.min_separation_km = min(self.min_separation_km, float(np.nanmin(gaps)))

    # ------------------------------------------------------------------ account

    def summary(self) -> dict[str, object]:
        """What the radio carried (``SwarmRadio``'s counts) and what it kept off the air."""
        return {
            "planes": [p.system_id for p in self.planes],
            **self.radio.stats.summary(),
            "not_relayed": dict(sorted(self.not_relayed.items())),
            "min_separation_km": None
            if math.isinf(self.min_separation_km)
            else round(self.min_separation_km, 4),
        }

    def progress_line(self) -> str:
        s = self.radio.stats
        located = sum(p.located for p in self.planes)
        return (
            f"radio-relay: {sum(p.connected for p in self.planes)}/{len(self.planes)} ports, "
            f"{located} located; frames {s.frames_sent} sent, {s.delivered} delivered, lost to "
            f"range {s.lost_to_range}, to loss {s.lost_to_loss}; not relayed "
            f"{sum(self.not_relayed.values())} (heartbeats {self.not_relayed['HEARTBEAT']})"
        )
