"""The payload simulator: the world and each vehicle's camera, for autopilots that run elsewhere.

Against real autopilots (ArduPlane SITL, hardware) the ground truth (targets, threats, the noisy
sensor of ``sim_gateway/world.py``) still has to live somewhere that is not the planner daemon.
This simulator follows each autopilot's own telemetry and speaks as that vehicle's camera,
MAVLink component 100 of system id i + 1, with the very encoding of our own simulator
(docs/mavlink.md, "Sensor looks" and "Engagements"):

* **Looks.** The world's clock is the most advanced of the vehicles' own clocks
  (``time_boot_ms`` of their GLOBAL_POSITION_INT): whenever it enters a new decision period
  (a multiple of ``step_s``) the world moves one decision step and every airborne vehicle
  (armed, at least ``min_look_altitude_m`` above home, its position fresh) takes one look at
  its latest reported position: CAMERA_IMAGE_CAPTURED with ``file_url`` ``look:dx,dy;...``,
  stamped with its own clock. A vehicle looks from the first period boundary after its first
  airborne fix. One instant for all (not each vehicle's own boundary): SITL instances boot
  one after the other, so their clocks differ by up to a decision period, and looks taken at
  each clock's own boundary reached the daemon staggered by up to a period; it then planned
  with positions a whole step old (measured with three ArduPlane SITL planes: 0.5 km behind).
* **Engagements.** COMMAND_LONG MAV_CMD_IMAGE_START_CAPTURE to (i + 1, 100) is resolved against
  ground truth at the vehicle's latest reported position (``World.engage``) and answered
  COMMAND_ACK from component 100, ``progress`` = sequence number modulo 256, ``result_param2`` =
  the serviced target id (0: none in range); a repeated sequence number replays its outcome.
* **Presence.** A HEARTBEAT (MAV_TYPE_CAMERA) from (i + 1, 100) every second once the vehicle is
  heard, so a ground station knows the vehicle has a camera, and an autopilot that routes
  MAVLink learns where component 100 lives.

Where it connects: any endpoint (``tcp:HOST:PORT``, ``udpin:HOST:PORT``, ``udpout:HOST:PORT``),
as many as needed; a vehicle is whoever's autopilot (component 1) is heard on it, and its camera
answers on the same endpoint. A udpout peer that talks only to whoever spoke first (PX4's
onboard link) is said hello every second until a vehicle answers on it, so the simulator may
start before the autopilot opens its port. For ArduPilot SITL the endpoint is each instance's
spare serial port, SERIAL1 on TCP 5762 + 10 i: ArduPilot routes MAVLink between its ports, so
the camera's messages reach the ground station on SERIAL0 and the ground station's commands to
component 100 reach the camera (measured with the V4.8.0-dev SITL: without a camera on a port
ArduPlane itself answers IMAGE_START_CAPTURE with FAILED; with one, it forwards the command and
stays silent). A TCP server that is not up yet (SITL opens SERIAL1 only once it boots) is
retried every 0.5 s, and reconnected if it goes away.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import selectors  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

import numpy as np  # noqa: E402

from mavlink_wire.links import (  # noqa: E402
    Address,
    Endpoint,
    EndpointError,
    TcpEndpoint,
    parse_endpoint,
)
from mavlink_wire.looks import look_messages  # noqa: E402
from mavlink_wire.protocol import CAMERA_COMPONENT_ID, component_heartbeat, mavlink  # noqa: E402
from planner.geodesy import geodetic_to_local_km  # noqa: E402
from planner.scenario import Scenario  # noqa: E402
from planner.sensor_model import SensorReport  # noqa: E402
from sim_gateway.camera import (  # noqa: E402
    EngagementLog,
    engagement_sequence,
    engagement_text,
)
from sim_gateway.target_account import TargetAccount  # noqa: E402
from sim_gateway.world import World  # noqa: E402

AUTOPILOT = 1
RECONNECT_S = 0.5
HEARTBEAT_PERIOD_S = 1.0
#: a vehicle whose latest position is older than this (wall s) does not look
FRESH_S = 2.0


@dataclass
class PayloadOptions:
    seed: int = 1
    vehicles: int | None = None  # default: the scenario's UAV count
    min_look_altitude_m: float = 10.0
    #: a world step per decision period of the leading vehicle clock, at most this many at once
    #: (a vehicle that rebooted or joined late must not fast-forward the world by hours)
    max_world_steps_at_once: int = 5


@dataclass
class _Channel:
    """One endpoint and its state (TCP: connected or not)."""

    spec: str
    endpoint: Endpoint
    connected: bool = False
    next_try_s: float = 0.0
    last_error: str = ""
    fd: int | None = None  # the socket registered with the selector
    hello_s: float = -1e9  # when we last said hello to a udpout peer that has not answered
    answered: bool = False  # a vehicle was heard on it (``_follow``)


class _Writer:
    """File-like sink for a pymavlink encoder: frames go to one channel and address."""

    def __init__(self, camera: FollowedCamera) -> None:
        self.camera = camera

    def write(self, frame: bytes) -> None:
        channel = self.camera.channel
        if channel is None or not channel.connected:
            return
        try:
            channel.endpoint.send_to(frame, self.camera.address)
        except EndpointError:
            channel.connected = False  # the receive side notices and reconnects


@dataclass
class FollowedCamera:
    """What the payload simulator knows of one vehicle, and that vehicle's camera."""

    index: int
    channel: _Channel | None = None
    address: Address | None = None
    armed: bool = False
    has_position: bool = False
    lat_e7: int = 0
    lon_e7: int = 0
    alt_mm: int = 0
    relative_alt_mm: int = 0
    time_boot_ms: int = 0
    period: int = -1  # the world period of its latest look (-1: not looking yet)
    airborne: bool = False
    heard_s: float = -1e9  # wall time of its latest position
    look_index: int = 0
    looks: int = 0
    engagements: EngagementLog = field(default_factory=EngagementLog)
    engaged: list[int] = field(default_factory=list)
    last_heartbeat_s: float = -1e9
    mav: mavlink.MAVLink | None = None

    @property
    def system_id(self) -> int:
        return self.index + 1

    @property
    def heard(self) -> bool:
        return self.channel is not None

    def encoder(self) -> mavlink.MAVLink:
        if self.mav is None:
            self.mav = mavlink.MAVLink(_Writer(self), self.system_id, CAMERA_COMPONENT_ID)
        return self.mav


class PayloadSimulator:
    """Follows N autopilots over MAVLink and plays their cameras in front of one world."""

    def __init__(self, scenario: Scenario, specs: list[str], options: PayloadOptions) -> None:
        if not specs:
            raise EndpointError("give at least one --connect endpoint (e.g. tcp:127.0.0.1:5762)")
        self.scenario = scenario
        self.options = options
        self.config = scenario.config
        count = options.vehicles or scenario.uav_count
        self.cameras = [FollowedCamera(i) for i in range(count)]
        self.world = World(scenario, options.seed)
        #: ground truth per target (never sent): the per-target account's truth half
        self.target_account = TargetAccount(self.world)
        self.world_period: int | None = None
        self.world_steps = 0
        self.step_ms = round(self.config.step_s * 1000)
        self.channels = [_Channel(spec, parse_endpoint(spec)) for spec in specs]
        self._selector = selectors.DefaultSelector()
        self.started_s = time.monotonic()
        self.looks_sent = 0
        self.engagement_requests = 0
        self.denied = 0

    # ------------------------------------------------------------------ connections

    def open(self) -> PayloadSimulator:
        """Open the UDP endpoints now (a port in use is an error at once); TCP ones connect in
        ``poll`` and retry until their server is up."""
        for channel in self.channels:
            if not isinstance(channel.endpoint, TcpEndpoint):
                channel.endpoint.open()
                self._attach(channel)
        return self

    def _attach(self, channel: _Channel) -> None:
        channel.connected = True
        channel.fd = channel.endpoint.fileno()
        self._selector.register(channel.fd, selectors.EVENT_READ, channel)
        self._say_hello(channel, time.monotonic())

    def _say_hello(self, channel: _Channel, now: float) -> None:
        """A udpout peer (PX4's onboard link) talks only to whoever talked to it first: say
        hello, again every heartbeat period until a vehicle answers on it (a hello sent before
        the autopilot opened its port is lost, and it would never answer)."""
        if channel.answered or not channel.endpoint.needs_first_word:
            return
        if now - channel.hello_s < HEARTBEAT_PERIOD_S:
            return
        channel.hello_s = now
        hello = mavlink.MAVLink(None, 0, CAMERA_COMPONENT_ID)
        channel.endpoint.send_to(component_heartbeat(hello, mavlink.MAV_TYPE_CAMERA), None)

    def _detach(self, channel: _Channel, reason: str) -> None:
        if channel.fd is not None:
            self._selector.unregister(channel.fd)  # by the number: the socket may be closed
            channel.fd = None
        channel.endpoint.close()
        channel.connected = False
        channel.last_error = reason
        channel.next_try_s = time.monotonic() + RECONNECT_S
        channel.endpoint.closed_reason = None  # noted here; the channel reconnects itself
        if isinstance(channel.endpoint, TcpEndpoint):
            channel.endpoint.parser = mavlink.MAVLink(None)
            channel.endpoint.parser.robust_parsing = True

    def _connect_tcp(self, now: float) -> None:
        for channel in self.channels:
            if channel.connected or now < channel.next_try_s:
                continue
            if not isinstance(channel.endpoint, TcpEndpoint):
                continue
            channel.endpoint.connect_timeout_s = 0.5
            try:
                channel.endpoint.open()
            except EndpointError as exc:
                channel.last_error = str(exc)
                channel.next_try_s = now + RECONNECT_S
                continue
            self._attach(channel)

    @property
    def unconnected(self) -> list[str]:
        return [c.spec for c in self.channels if not c.connected]

    def close(self) -> None:
        self._selector.close()
        for channel in self.channels:
            channel.endpoint.close()

    def __enter__(self) -> PayloadSimulator:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the loop

    def poll(self, timeout_s: float = 0.05) -> None:
        """Connect what is not connected, read every endpoint once, send due heartbeats."""
        now = time.monotonic()
        self._connect_tcp(now)
        events = self._selector.select(timeout_s) if self._selector.get_map() else []
        if not events and not self._selector.get_map():
            time.sleep(timeout_s)
        for key, _ in events:
            channel: _Channel = key.data
            try:
                received = channel.endpoint.receive()
            except EndpointError as exc:
                self._detach(channel, str(exc))
                continue
            for msg, address in received:
                self._handle(msg, channel, address)
            if channel.endpoint.closed_reason is not None:  # a TCP server went away
                self._detach(channel, channel.endpoint.closed_reason)
        self._heartbeats(time.monotonic())

    def run(
        self,
        until: Callable[[], bool] = lambda: False,
        on_progress: Callable[[PayloadSimulator], None] | None = None,
        progress_period_s: float = 5.0,
    ) -> None:
        next_progress = time.monotonic() + progress_period_s
        while not until():
            self.poll()
            if on_progress is not None and time.monotonic() >= next_progress:
                next_progress += progress_period_s
                on_progress(self)

    def _heartbeats(self, now: float) -> None:
        for channel in self.channels:
            if channel.connected:
                self._say_hello(channel, now)
        for camera in self.cameras:
            if camera.heard and now - camera.last_heartbeat_s >= HEARTBEAT_PERIOD_S:
                camera.last_heartbeat_s = now
                camera.encoder().heartbeat_send(
                    mavlink.MAV_TYPE_CAMERA, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                    mavlink.MAV_STATE_ACTIVE,
                )  # fmt: skip

    # ------------------------------------------------------------------ messages

    def _camera_of(self, sysid: int) -> FollowedCamera | None:
        return self.cameras[sysid - 1] if 1 <= sysid <= len(self.cameras) else None

    def _handle(self, msg: mavlink.MAVLink_message, channel: _Channel, address: Address | None):
        kind = msg.get_type()
        if kind == "COMMAND_LONG":
            camera = self._camera_of(msg.target_system)
            if camera is not None and msg.target_component == CAMERA_COMPONENT_ID:
                self._follow(camera, channel, address, heard_from_autopilot=False)
                self._command(camera, msg)
            return
        camera = self._camera_of(msg.get_srcSystem())
        if camera is None or msg.get_srcComponent() != AUTOPILOT:
            return
        if kind == "HEARTBEAT":
            if msg.type in (mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_CAMERA):
                return
            self._follow(camera, channel, address, heard_from_autopilot=True)
            camera.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        elif kind == "GLOBAL_POSITION_INT" and camera.heard:
            self._position(camera, msg)

    def _follow(
        self,
        camera: FollowedCamera,
        channel: _Channel,
        address: Address | None,
        heard_from_autopilot: bool,
    ) -> None:
        """The vehicle's camera answers where its autopilot was last heard."""
        channel.answered = True
        if camera.channel is None or heard_from_autopilot:
            camera.channel, camera.address = channel, address

    def _position(self, camera: FollowedCamera, msg: mavlink.MAVLink_message) -> None:
        if not (-90e7 <= msg.lat <= 90e7 and -180e7 <= msg.lon <= 180e7):
            return
        camera.has_position = True
        camera.lat_e7, camera.lon_e7 = msg.lat, msg.lon
        camera.alt_mm, camera.relative_alt_mm = msg.alt, msg.relative_alt
        camera.time_boot_ms = msg.time_boot_ms
        camera.heard_s = time.monotonic()
        camera.airborne = (
            camera.armed and msg.relative_alt >= self.options.min_look_altitude_m * 1000
        )
        moved = self._advance_world(msg.time_boot_ms // self.step_ms)
        if camera.airborne and camera.period < 0 and self.world_period is not None:
            camera.period = self.world_period  # looks from the next boundary on
        if moved:
            self._look_all()

    def _advance_world(self, period: int) -> bool:
        """Move the world to the leading clock's decision period; True if it moved."""
        if self.world_period is None:
            self.world_period = period
            return False
        if period <= self.world_period:
            return False
        steps = min(period - self.world_period, self.options.max_world_steps_at_once)
        self.world_period = period
        for _ in range(steps):
            self.world.step(self.config.step_s)
            self.world_steps += 1
        return True

    def _look_all(self) -> None:
        """One look for every airborne vehicle heard within the last ``FRESH_S``."""
        now = time.monotonic()
        looked = []
        for camera in self.cameras:
            fresh = now - camera.heard_s <= FRESH_S
            if camera.airborne and fresh and 0 <= camera.period < self.world_period:
                camera.period = self.world_period
                looked.append((camera, *self._look(camera)))
        if looked:  # the account's truth of this step: who looked from where, what they saw
            stamps, counts = np.unique([c.time_boot_ms for c, _, _ in looked], return_counts=True)
            self.target_account.observe(
                self.world_steps,
                np.array([xy for _, xy, _ in looked]),
                None,
                [report for _, _, report in looked],
                int(stamps[np.argmax(counts)]),  # as the daemon's look_times_ms picks one
            )

    def _xy_km(self, camera: FollowedCamera) -> np.ndarray:
        x, y = geodetic_to_local_km(camera.lat_e7 / 1e7, camera.lon_e7 / 1e7, self.scenario.origin)
        return np.array([float(x[0]), float(y[0])])

    def _look(self, camera: FollowedCamera) -> tuple[np.ndarray, SensorReport]:
        """One look of ``camera`` sent; its position (km) and the sensor's report."""
        xy = self._xy_km(camera)
        report = self.world.sense(xy[None, :])[0]
        look_cell = self.world.grid.cell_of(xy[None, :])[0]
        detected = report.cells[report.detected] - look_cell
        for message in look_messages(
            ((int(dx), int(dy)) for dx, dy in detected),
            camera.look_index,
            camera.time_boot_ms,
            int(time.time() * 1e6),
            camera.lat_e7,
            camera.lon_e7,
            camera.alt_mm,
            camera.relative_alt_mm,
        ):
            camera.encoder().send(message)
        camera.look_index += 1
        camera.looks += 1
        self.looks_sent += 1
        return xy, report

    def _command(self, camera: FollowedCamera, msg: mavlink.MAVLink_message) -> None:
        mav = camera.encoder()
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        if msg.command != mavlink.MAV_CMD_IMAGE_START_CAPTURE:
            mav.command_ack_send(
                msg.command, mavlink.MAV_RESULT_UNSUPPORTED, target_system=peer[0],
                target_component=peer[1],
            )  # fmt: skip
            return
        self.engagement_requests += 1
        sequence = engagement_sequence(msg.param2, msg.param3, msg.param4)
        if sequence is None or not camera.has_position:
            self.denied += 1
            mav.command_ack_send(
                msg.command, mavlink.MAV_RESULT_DENIED, target_system=peer[0],
                target_component=peer[1],
            )  # fmt: skip
            return
        xy = self._xy_km(camera)
        outcome, replay = camera.engagements.resolve(
            sequence, lambda: self.world.engage(xy, self.world_steps)
        )
        mav.command_ack_send(
            msg.command,
            mavlink.MAV_RESULT_ACCEPTED,
            progress=sequence % 256,
            result_param2=outcome.target_id,
            target_system=peer[0],
            target_component=peer[1],
        )
        if not replay:
            if outcome.success:
                camera.engaged.append(outcome.target_id)
            self.target_account.record_engagement(self.world_steps, camera.index, outcome)
            mav.statustext_send(
                mavlink.MAV_SEVERITY_INFO, engagement_text(sequence, outcome).encode()
            )

    # ------------------------------------------------------------------ account

    def summary(self) -> dict:
        """Counters and the ground truth of what was engaged (never sent over MAVLink)."""
        engaged = [int(t) for t in self.world.target_ids[~self.world.alive]]
        return {
            "vehicles": len(self.cameras),
            "vehicles_heard": sum(c.heard for c in self.cameras),
            "world_steps": self.world_steps,
            "looks_sent": self.looks_sent,
            "looks_per_vehicle": [c.looks for c in self.cameras],
            "engagement_requests": self.engagement_requests,
            "engagement_requests_denied": self.denied,
            "targets_engaged": sorted(engaged),
            "engaged_value": float(self.world.values[~self.world.alive].sum()),
            "wall_s": round(time.monotonic() - self.started_s, 1),
        }

    def progress_line(self) -> str:
        heard = sum(c.heard for c in self.cameras)
        airborne = sum(c.airborne and c.period >= 0 for c in self.cameras)
        waiting = f"; waiting for {', '.join(self.unconnected)}" if self.unconnected else ""
        return (
            f"payload: {heard}/{len(self.cameras)} vehicles heard, {airborne} looking, world "
            f"step {self.world_steps}, looks {self.looks_sent}, engagements "
            f"{len(self.world.alive) - int(self.world.alive.sum())}{waiting}"
        )
