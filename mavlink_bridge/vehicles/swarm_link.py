"""All the daemon's endpoints and the vehicles heard on them, pumped from one loop.

``SwarmLink.pump(timeout)`` waits for datagrams on every endpoint, parses them, logs every frame
to the .tlog, routes each message to the ``VehicleState`` of its (link, system id)
(``vehicle_key.py``; a new vehicle is registered, and bound to its address, by its autopilot's
HEARTBEAT that carries a vehicle type: ``claims_vehicle``), and sends the daemon's own GCS
heartbeat at 1 Hz.

Only what is authentic or plausible changes a vehicle's state (``_dispatch``): with signing on,
an unsigned frame (RADIO_STATUS / RADIO, which pass the signature check unsigned) changes
nothing and binds nothing; every other frame must come from the address its vehicle component
is bound to and pass the plausibility rules (``telemetry_plausibility.py``). What fails is
logged and counted.
"""

from __future__ import annotations

import contextlib
import selectors
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from mavlink_bridge.vehicles.telemetry_plausibility import PlausibilityFilter
from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_wire.links import Address, Endpoint, VehicleLink, open_endpoint
from mavlink_wire.protocol import AUTOPILOT_COMPONENT_ID, mavlink
from mavlink_wire.signing import SignatureCheck, is_signed, sign_outgoing
from mavlink_wire.tlog import TlogWriter

#: MAV_TYPEs of vehicles (what an autopilot's HEARTBEAT says it flies or drives). Not: generic,
#: ground stations, companion computers, gimbals, cameras, ADS-B, trackers and other parts.
_VEHICLE_TYPE_NAMES = [
    "FIXED_WING", "QUADROTOR", "COAXIAL", "HELICOPTER", "AIRSHIP", "FREE_BALLOON", "ROCKET",
    "GROUND_ROVER", "SURFACE_BOAT", "SUBMARINE", "HEXAROTOR", "OCTOROTOR", "TRICOPTER",
    "FLAPPING_WING", "KITE", "VTOL_DUOROTOR", "VTOL_QUADROTOR", "VTOL_TILTROTOR",
    "VTOL_RESERVED2", "VTOL_RESERVED3", "VTOL_RESERVED4", "VTOL_RESERVED5", "PARAFOIL",
    "DODECAROTOR", "DECAROTOR", "GENERIC_MULTIROTOR", "VTOL_GYRODYNE",
]  # fmt: skip
VEHICLE_TYPES = frozenset(
    getattr(mavlink, f"MAV_TYPE_{name}")
    for name in _VEHICLE_TYPE_NAMES
    if hasattr(mavlink, f"MAV_TYPE_{name}")  # (newer ones are missing in older pymavlink)
)
#: MAV_AUTOPILOTs of a real autopilot (all named ones but INVALID, what non-autopilots send)
AUTOPILOTS = frozenset(
    value
    for value, entry in mavlink.enums["MAV_AUTOPILOT"].items()
    if value != mavlink.MAV_AUTOPILOT_INVALID and not entry.name.endswith("ENUM_END")
)
#: HEARTBEAT ``mavlink_version``: 3 for MAVLink 1 and 2 alike (set by the protocol, not the user)
_MAVLINK_VERSION = 3


def claims_vehicle(msg: mavlink.MAVLink_message) -> bool:
    """An autopilot's HEARTBEAT that says it is a vehicle: component 1 (MAV_COMP_ID_AUTOPILOT1),
    a vehicle type, a real autopilot, the protocol's version byte. Only such a frame makes (or
    moves) a vehicle; a ground station's, a companion's or a fuzzed HEARTBEAT does not."""
    return (
        msg.get_type() == "HEARTBEAT"
        and msg.get_srcComponent() == AUTOPILOT_COMPONENT_ID
        and msg.type in VEHICLE_TYPES
        and msg.autopilot in AUTOPILOTS
        and msg.mavlink_version == _MAVLINK_VERSION
    )


class SwarmLink:
    """The endpoints, the vehicles by (link, system id), and the receive loop. ``links[k]`` is
    the network of endpoint ``k`` (``FleetMap.link_of_endpoint``; default: all one network, 0):
    a vehicle is told apart by its network and its system id."""

    def __init__(
        self,
        endpoints: list[Endpoint],
        tlog: TlogWriter | None = None,
        heartbeat_period_s: float = 1.0,
        accept_vehicle: Callable[[VehicleKey], bool] | None = None,
        signing_key: bytes | None = None,
        plausibility: PlausibilityFilter | None = None,
        may_move: Callable[[VehicleState], bool] | None = None,
        links: list[int] | None = None,
        source: tuple[int, int] | None = None,
    ) -> None:
        self.endpoints = endpoints
        #: our MAVLink (system, component) on every link (None: a ground station's, 255/190)
        self.source = source
        links = links or [0] * len(endpoints)
        self._link_of = {id(e): k for e, k in zip(endpoints, links, strict=True)}
        #: whether a vehicle's binding may move to a new address (the daemon: only a vehicle
        #: it counts as gone); without it, the bound address's silence alone decides
        self.may_move = may_move or (lambda vehicle: True)
        self.plausibility = plausibility or PlausibilityFilter()
        # MAVLink 2 signing: every frame we send is signed, every frame we hear is checked
        self.signing_key = signing_key
        self.signature_check = SignatureCheck(signing_key) if signing_key is not None else None
        for endpoint in endpoints:
            endpoint.signature_check = self.signature_check
        self.tlog = tlog
        self.heartbeat_period_s = heartbeat_period_s
        self.accept_vehicle = accept_vehicle or (lambda key: 1 <= key.system_id < 250)
        self.vehicles: dict[VehicleKey, VehicleState] = {}
        self._selector = selectors.DefaultSelector()
        self._watched: dict[int, int] = {}  # id(endpoint) -> the file descriptor selected on
        for endpoint in endpoints:
            self._watch(endpoint)
        self._last_heartbeat_s = -1e9
        # udpout peers that wait for our first word get their own GCS link until a vehicle answers
        self._openers = [
            VehicleLink(0, e, None, tlog, source=source) for e in endpoints if e.needs_first_word
        ]
        for opener in self._openers:
            self._secure(opener)
        self.messages_received = 0
        #: called with (vehicle, message) after the vehicle's state took each message in
        #: (e.g. the continuous safety account, track_audit.py)
        self.listeners: list[Callable[[VehicleState, mavlink.MAVLink_message], None]] = []
        #: called with every TUNNEL frame heard (signed, with signing on) instead of routing it
        #: to a vehicle: the swarm link's frames, relayed by a plane's autopilot or radio from the
        #: other planes' nodes (a planner node's, ``mavlink_bridge/mission/onboard_planner.py``)
        self.tunnel_listeners: list[Callable[[mavlink.MAVLink_message], None]] = []

    @classmethod
    def open(cls, specs: Iterable[str], tlog: TlogWriter | None = None, **kwargs: Any) -> SwarmLink:
        """Open every endpoint (closing those already opened if one fails)."""
        opened: list[Endpoint] = []
        try:
            for spec in specs:
                opened.append(open_endpoint(spec))
        except Exception:
            for endpoint in opened:
                endpoint.close()
            raise
        return cls(opened, tlog, **kwargs)

    def vehicle(self, system_id: int, link: int = 0) -> VehicleState | None:
        """The vehicle of ``system_id`` on network ``link`` (0: the only one), if heard."""
        return self.vehicles.get(VehicleKey(link, system_id))

    def describe(self) -> str:
        """The endpoints as the user gave them, with the real port of udpin:...:0."""
        parts = []
        for e in self.endpoints:
            kind = e.spec.split(":")[0]
            parts.append(f"{kind}:{e.host}:{e.port}")
        return ", ".join(parts)

    # ------------------------------------------------------------------ receive

    def _watch(self, endpoint: Endpoint) -> None:
        fd = endpoint.fileno()
        self._selector.register(fd, selectors.EVENT_READ, endpoint)
        self._watched[id(endpoint)] = fd

    def _unwatch(self, endpoint: Endpoint) -> None:
        fd = self._watched.pop(id(endpoint), None)
        if fd is not None:
            self._selector.unregister(fd)

    def _reconnect_due(self) -> None:
        """Connections that went away (a TCP vehicle that closed) are tried again, with backoff."""
        now = time.monotonic()
        for endpoint in self.endpoints:
            if endpoint.closed_reason is None:
                continue
            self._unwatch(endpoint)  # (it may have gone away while sending)
            if endpoint.reconnect(now):
                self._watch(endpoint)

    def pump(self, timeout_s: float = 0.0) -> int:
        """Receive and dispatch whatever arrives within ``timeout_s``; returns the message count.
        An endpoint whose connection goes away stops being read (its vehicles fall silent) until
        it is connected again."""
        self._reconnect_due()
        self.send_heartbeat_if_due()
        count = 0
        for key, _ in self._selector.select(max(0.0, timeout_s)):
            endpoint: Endpoint = key.data
            now = time.monotonic()
            for msg, address in endpoint.receive():
                self._dispatch(msg, endpoint, address, now)
                count += 1
            if endpoint.closed_reason is not None:
                self._unwatch(endpoint)
        self.messages_received += count
        self.send_heartbeat_if_due()
        return count

    def pump_until(self, done: Callable[[], bool], timeout_s: float, poll_s: float = 0.05) -> bool:
        """Pump until ``done()`` is true (returns True) or ``timeout_s`` passes (returns False)."""
        deadline = time.monotonic() + timeout_s
        while not done():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            self.pump(min(poll_s, left))
        return True

    def _dispatch(
        self, msg: mavlink.MAVLink_message, endpoint: Endpoint, address: Address | None, now: float
    ) -> None:
        if self.tlog is not None:
            self.tlog.write(msg.get_msgbuf())
        trust = self.plausibility
        if self.signature_check is not None and not is_signed(msg.get_msgbuf()):
            trust.counts.unsigned_ignored += 1  # authentic frames are signed: believe nothing
            return
        if self.tunnel_listeners and msg.get_type() == "TUNNEL":
            for listen in self.tunnel_listeners:
                listen(msg)
            return
        sysid, compid = msg.get_srcSystem(), msg.get_srcComponent()
        key = VehicleKey(self._link_of[id(endpoint)], sysid)
        where = (id(endpoint), address)
        vehicle = self.vehicles.get(key)
        if vehicle is None:
            if not (claims_vehicle(msg) and self.accept_vehicle(key)):
                trust.unbound(key, where)  # nothing binds but a vehicle's HEARTBEAT (rule 2)
                return
            if not trust.admit(key, msg, now):
                return
            link = self._secure(
                VehicleLink(sysid, endpoint, address, self.tlog, source=self.source)
            )
            vehicle = VehicleState(sysid, link, key=key)
            self.vehicles[key] = vehicle
            trust.admit_address(key, compid, where, now, announces=True)
        else:
            announces, may_move = self._announces(vehicle, msg), self.may_move(vehicle)
            verdict = trust.admit_address(key, compid, where, now, announces, may_move)
            if verdict in ("refused", "unbound") or not trust.admit(key, msg, now):
                return
            if compid != AUTOPILOT_COMPONENT_ID:
                self._route_component(vehicle, compid, endpoint, address)
            elif verdict == "moved":
                vehicle.link.moved(endpoint, address)  # a reboot, a new socket: replies follow
        vehicle.handle(msg, now)
        for listen in self.listeners:
            listen(vehicle, msg)

    def _route_component(
        self, vehicle: VehicleState, component: int, endpoint: Endpoint, address: Address | None
    ) -> None:
        """Route by (system, component): a component heard where its autopilot is not (a
        payload simulator's camera on its own link) is answered where it is heard; one heard
        on the autopilot's link (routed through the autopilot, as ArduPilot does) shares it."""
        on_autopilot_link = vehicle.link.endpoint is endpoint and (
            address is None or address == vehicle.link.address
        )
        if on_autopilot_link:
            vehicle.component_links.pop(component, None)
            return
        link = vehicle.component_links.get(component)
        if link is None:
            vehicle.component_links[component] = self._secure(
                VehicleLink(vehicle.system_id, endpoint, address, self.tlog, source=self.source)
            )
        elif link.endpoint is not endpoint or (address is not None and link.address != address):
            link.moved(endpoint, address)

    def _secure(self, link: VehicleLink) -> VehicleLink:
        """Sign what ``link`` sends (link id = the vehicle's system id: one stream each)."""
        if self.signing_key is not None:
            sign_outgoing(link.mav, self.signing_key, link.system_id)
        return link

    @staticmethod
    def _announces(vehicle: VehicleState, msg: mavlink.MAVLink_message) -> bool:
        """``msg`` is a HEARTBEAT that may bind (or move) its component of ``vehicle``: the
        autopilot's as a vehicle of the type it registered with; another component's own."""
        if msg.get_srcComponent() == AUTOPILOT_COMPONENT_ID:
            return claims_vehicle(msg) and msg.type == vehicle.vehicle_type
        return msg.get_type() == "HEARTBEAT" and msg.type != mavlink.MAV_TYPE_GCS

    # ------------------------------------------------------------------ send

    def send_heartbeat_if_due(self) -> None:
        now = time.monotonic()
        if now - self._last_heartbeat_s >= self.heartbeat_period_s:
            self._last_heartbeat_s = now
            self.send_heartbeat()

    def send_heartbeat(self) -> None:
        """Our GCS heartbeat to every vehicle (and to udpout peers not heard from yet)."""
        links = [v.link for v in self.vehicles.values()]
        served = {id(v.link.endpoint) for v in self.vehicles.values()}
        links += [o for o in self._openers if id(o.endpoint) not in served]
        for link in links:
            link.mav.heartbeat_send(
                mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
            )

    @contextlib.contextmanager
    def keepalive(self) -> Iterator[None]:
        """While the caller computes without touching the link (a decision step of hundreds of
        UAVs, the ways home of a large swarm: many seconds), a thread sends our GCS heartbeat
        when due, so that no vehicle sees us silent: an autopilot's GCS failsafe, a lockstep
        simulator's ``--lockstep-timeout`` (it lets its clock run free after 10 s without a word
        from us). Nothing else may use the link meanwhile (the heartbeat takes the vehicles'
        encoders); the thread is stopped before this returns."""
        stop = threading.Event()

        def beat() -> None:
            while not stop.wait(max(0.05, self.heartbeat_period_s / 2)):
                self.send_heartbeat_if_due()

        thread = threading.Thread(target=beat, name="gcs-heartbeat", daemon=True)
        thread.start()
        try:
            yield
        finally:
            stop.set()
            thread.join()

    def close(self) -> None:
        self._selector.close()
        for endpoint in self.endpoints:
            endpoint.close()
