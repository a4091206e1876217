"""What the daemon knows of one vehicle, kept up to date by one small handler per message.

Handlers are named after the message they handle (``on_heartbeat``, ``on_global_position_int``,
``on_command_ack``, ``on_camera_image_captured``, ...). ``handle(msg)`` dispatches; messages the
daemon has no use for are ignored.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from mavlink_bridge.vehicles.param_encoding import decode_param
from mavlink_bridge.vehicles.telemetry_plausibility import on_earth
from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_wire.links import VehicleLink
from mavlink_wire.looks import look_part, parse_look_offsets
from mavlink_wire.protocol import AUTOPILOT_COMPONENT_ID, CAMERA_COMPONENT_ID, mavlink

#: A look number this far beyond the newest one is refused (a real camera counts one by one).
MAX_LOOK_JUMP = 10_000
#: Without EXTENDED_SYS_STATE, an armed vehicle this high above home counts as airborne.
AIRBORNE_MIN_ALT_M = 5.0


@dataclass
class Look:
    """One sensor look reported as CAMERA_IMAGE_CAPTURED (see docs/daemon.md)."""

    index: int
    lat_deg: float
    lon_deg: float
    offsets: list[tuple[int, int]]  # detected cells relative to the look cell
    received_s: float  # wall clock (monotonic) when the first part arrived
    time_boot_ms: int = 0  # the vehicle's clock when it looked


@dataclass
class CommandAck:
    """The latest COMMAND_ACK for one (component, command) of a vehicle."""

    command: int
    result: int
    result_param2: int
    received_s: float
    serial: int  # increases with every ack, so a waiter can tell a new one from an old one
    component: int = AUTOPILOT_COMPONENT_ID
    progress: int = 0  # result_param1; the camera echoes an engagement's sequence number here


@dataclass
class VehicleState:
    """Telemetry, status and protocol state of one vehicle: ``system_id`` addresses it on its
    network, ``key`` (link, system id) tells it apart from every other (vehicle_key.py)."""

    system_id: int
    link: VehicleLink
    key: VehicleKey = VehicleKey(0, 0)  # (0, system_id) unless given
    last_heard_s: float = field(default_factory=time.monotonic)
    heartbeats: int = 0
    vehicle_type: int = -1
    autopilot: int = -1
    base_mode: int = 0
    custom_mode: int = -1
    system_status: int = mavlink.MAV_STATE_UNINIT
    # position (GLOBAL_POSITION_INT)
    has_position: bool = False
    lat_deg: float = 0.0
    lon_deg: float = 0.0
    relative_alt_m: float = 0.0
    alt_amsl_m: float = 0.0  # above mean sea level (PX4 takes AMSL altitudes)
    vn_mps: float = 0.0
    ve_mps: float = 0.0
    heading_cdeg: int = 65535
    time_boot_ms: int = 0
    position_s: float = 0.0
    # home (HOME_POSITION)
    home: tuple[float, float, float] | None = None
    #: EXTENDED_SYS_STATE landed_state (MAV_LANDED_STATE_*), UNDEFINED until heard
    landed_state: int = mavlink.MAV_LANDED_STATE_UNDEFINED
    #: SYSTEM_TIME time_boot_ms: the vehicle's clock, also between position reports
    system_time_boot_ms: int = 0
    # status texts (STATUSTEXT), newest last
    statustexts: deque[tuple[float, int, str]] = field(default_factory=lambda: deque(maxlen=50))
    # command acks by (component, command)
    acks: dict[tuple[int, int], CommandAck] = field(default_factory=dict)
    ack_serial: int = 0
    #: the newest acks in arrival order: a waiter finds its own among late and duplicated ones
    ack_log: deque[CommandAck] = field(default_factory=lambda: deque(maxlen=64))
    # sensor looks by image index
    looks: dict[int, Look] = field(default_factory=dict)
    latest_look: int = -1
    # mission protocol (fence upload)
    mission_requests: deque[tuple[int, int]] = field(default_factory=deque)  # (seq, mission_type)
    mission_ack: tuple[int, int] | None = None  # (type, mission_type)
    lost: bool = False
    # readiness (mavlink_bridge/vehicles/readiness.py): SYS_STATUS sensor bits, GPS_RAW_INT fix type
    sensors_present: int = 0
    sensors_enabled: int = 0
    sensors_health: int = 0
    has_sys_status: bool = False
    gps_fix_type: int = -1  # -1: no GPS_RAW_INT heard
    #: SYS_STATUS battery_remaining, % (-1: not reported); the simulator reports the share of
    #: its range (L_max) left
    battery_pct: int = -1
    #: parameters the vehicle reported (PARAM_VALUE), by name (gcs_failsafe.py, airframe.py)
    params: dict[str, float] = field(default_factory=dict)
    # components other than the autopilot heard by HEARTBEAT (100: a camera), by component id
    components: dict[int, int] = field(default_factory=dict)
    #: links of components heard on another link than the autopilot (swarm_link routes by
    #: system and component id); a command to such a component goes there
    component_links: dict[int, VehicleLink] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.key.system_id == 0:
            self.key = VehicleKey(0, self.system_id)

    # ------------------------------------------------------------------ derived

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    @property
    def standby_or_active(self) -> bool:
        """Initialisation finished: the autopilot is ready to upload and arm (or already flying)."""
        return self.system_status in (mavlink.MAV_STATE_STANDBY, mavlink.MAV_STATE_ACTIVE)

    @property
    def fence_breached(self) -> bool:
        """Its geofence reports a breach (SYS_STATUS: GEOFENCE enabled and not healthy)."""
        bit = mavlink.MAV_SYS_STATUS_GEOFENCE
        return bool(self.sensors_enabled & bit) and not self.sensors_health & bit

    @property
    def airborne(self) -> bool:
        """Armed and flying: more than AIRBORNE_MIN_ALT_M above home, or in the air by
        EXTENDED_SYS_STATE (either says so: one of them may be stale, EXTENDED_SYS_STATE comes
        rarely). A disarmed vehicle is never airborne (it must never be sent RTL)."""
        if not self.armed:
            return False
        in_air = self.landed_state not in (
            mavlink.MAV_LANDED_STATE_ON_GROUND,
            mavlink.MAV_LANDED_STATE_UNDEFINED,
        )
        return in_air or (self.has_position and self.relative_alt_m > AIRBORNE_MIN_ALT_M)

    @property
    def speed_mps(self) -> float:
        """Ground speed from the last position report (the airspeed, without wind)."""
        return math.hypot(self.vn_mps, self.ve_mps)

    @property
    def course_rad(self) -> float:
        """Course over ground from the last position report, rad from east (counter-clockwise);
        meaningful while it moves (``speed_mps`` above 1 m/s)."""
        return math.atan2(self.vn_mps, self.ve_mps)

    @property
    def clock_ms(self) -> int:
        """The vehicle's own clock (time_boot_ms) as last reported, by position or SYSTEM_TIME."""
        return max(self.time_boot_ms, self.system_time_boot_ms)

    def link_for(self, component: int) -> VehicleLink:
        """Where a message to ``component`` of this vehicle goes."""
        return self.component_links.get(component, self.link)

    def camera_heard(self) -> bool:
        """Whether a camera (component 100) of the vehicle was ever heard: a heartbeat, a look
        or an acknowledgement of its own."""
        return (
            CAMERA_COMPONENT_ID in self.components
            or self.latest_look >= 0
            or any(ack.component == CAMERA_COMPONENT_ID for ack in self.ack_log)
        )

    def silent_for(self, now_s: float | None = None) -> float:
        return (time.monotonic() if now_s is None else now_s) - self.last_heard_s

    def prearm_reasons(self, since_s: float = 0.0) -> list[str]:
        """The newest batch of STATUSTEXTs since ``since_s`` that explain an arming refusal
        (``PreArm: ...``; ``Arm: ...`` answers a refused arm). ArduPilot repeats its failing
        checks every 30 s of its clock, so the newest batch (within 1 s) is what still fails."""
        texts = [
            (when, text)
            for when, _severity, text in self.statustexts
            if when >= since_s and text.lower().startswith(("prearm", "arm:"))
        ]
        if not texts:
            return []
        newest = texts[-1][0]
        return list(dict.fromkeys(text for when, text in texts if when >= newest - 1.0))

    # ------------------------------------------------------------------ dispatch

    def handle(self, msg: mavlink.MAVLink_message, now_s: float | None = None) -> None:
        """Update the state from one message of this vehicle (any of its components)."""
        self.last_heard_s = time.monotonic() if now_s is None else now_s
        handler: Callable[[VehicleState, mavlink.MAVLink_message], None] | None = _HANDLERS.get(
            msg.get_type()
        )
        if handler is not None:
            handler(self, msg)

    # ------------------------------------------------------------------ handlers

    def on_heartbeat(self, msg: mavlink.MAVLink_heartbeat_message) -> None:
        if msg.get_srcComponent() != AUTOPILOT_COMPONENT_ID:
            # the camera's (or another component's) heartbeat says nothing of the vehicle, only
            # that the component is there (its MAV_TYPE)
            self.components[msg.get_srcComponent()] = msg.type
            return
        self.heartbeats += 1
        self.vehicle_type = msg.type
        self.autopilot = msg.autopilot
        self.base_mode = msg.base_mode
        self.custom_mode = msg.custom_mode
        self.system_status = msg.system_status

    def on_global_position_int(self, msg: mavlink.MAVLink_global_position_int_message) -> None:
        """A position fix. Whether it is believed at all (time order, speed, fields, a clock
        restarted by a reboot) is decided before, by telemetry_plausibility.py."""
        if not on_earth(msg.lat, msg.lon):
            return  # not a position (a corrupt or hostile frame)
        self.has_position = True
        self.lat_deg = msg.lat * 1e-7
        self.lon_deg = msg.lon * 1e-7
        self.relative_alt_m = msg.relative_alt * 1e-3
        self.alt_amsl_m = msg.alt * 1e-3
        self.vn_mps = msg.vx * 1e-2
        self.ve_mps = msg.vy * 1e-2
        self.heading_cdeg = msg.hdg
        self.time_boot_ms = msg.time_boot_ms
        self.position_s = self.last_heard_s

    def on_home_position(self, msg: mavlink.MAVLink_home_position_message) -> None:
        if not on_earth(msg.latitude, msg.longitude):
            return  # not a position: a corrupt or hostile frame must not become a UAV's start
        self.home = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)

    def on_param_value(self, msg: mavlink.MAVLink_param_value_message) -> None:
        """A parameter's current value (the answer to PARAM_SET / PARAM_REQUEST_READ)."""
        if msg.get_srcComponent() != AUTOPILOT_COMPONENT_ID:
            return
        raw = msg.param_id
        name = (raw if isinstance(raw, str) else raw.decode("ascii", "replace")).rstrip("\x00")
        if math.isfinite(msg.param_value):
            self.params[name] = float(decode_param(self.autopilot, msg.param_value, msg.param_type))

    def on_extended_sys_state(self, msg: mavlink.MAVLink_extended_sys_state_message) -> None:
        if msg.get_srcComponent() == AUTOPILOT_COMPONENT_ID:
            self.landed_state = msg.landed_state

    def on_system_time(self, msg: mavlink.MAVLink_system_time_message) -> None:
        if msg.get_srcComponent() != AUTOPILOT_COMPONENT_ID:
            return
        if msg.time_boot_ms < self.system_time_boot_ms - 60_000:
            self.system_time_boot_ms = 0  # its clock restarted (a reboot)
        self.system_time_boot_ms = max(self.system_time_boot_ms, msg.time_boot_ms)

    def on_statustext(self, msg: mavlink.MAVLink_statustext_message) -> None:
        text = msg.text if isinstance(msg.text, str) else msg.text.decode("utf-8", "replace")
        self.statustexts.append((self.last_heard_s, msg.severity, text.strip("\x00 ")))

    def on_command_ack(self, msg: mavlink.MAVLink_command_ack_message) -> None:
        self.ack_serial += 1
        ack = CommandAck(
            msg.command,
            msg.result,
            msg.result_param2,
            self.last_heard_s,
            self.ack_serial,
            msg.get_srcComponent(),
            msg.progress,
        )
        self.acks[(ack.component, msg.command)] = ack
        self.ack_log.append(ack)

    def on_camera_image_captured(self, msg: mavlink.MAVLink_camera_image_captured_message) -> None:
        """A sensor look, possibly in parts. Parts may come twice (a duplicating link) or out of
        order (a continuation before its first part): detections are merged as a set, and a
        look counts as new (``latest_look``) once its first part is in."""
        if msg.get_srcComponent() != CAMERA_COMPONENT_ID or msg.capture_result != 1:
            return
        url = (
            msg.file_url
            if isinstance(msg.file_url, str)
            else msg.file_url.decode("ascii", "replace")
        )
        url = url.rstrip("\x00")
        part = look_part(url)
        if part is None:
            return  # an ordinary photo, not a sensor look
        first, offsets_text = part
        index = msg.image_index
        if not on_earth(msg.lat, msg.lon):
            return  # not a position: a corrupt or hostile frame
        if self.latest_look >= 0 and index > self.latest_look + MAX_LOOK_JUMP:
            return  # a look number far ahead of any plausible one would stall every later look
        offsets = parse_look_offsets(offsets_text)
        look = self.looks.get(index)
        if look is None:
            look = Look(
                index, msg.lat * 1e-7, msg.lon * 1e-7, [], self.last_heard_s, msg.time_boot_ms
            )
            self.looks[index] = look
        look.offsets = list(dict.fromkeys([*look.offsets, *offsets]))
        if first and index > self.latest_look:
            self.latest_look = index
            for old in [k for k in self.looks if k < index - 20]:
                del self.looks[old]

    def on_sys_status(self, msg: mavlink.MAVLink_sys_status_message) -> None:
        if msg.get_srcComponent() != AUTOPILOT_COMPONENT_ID:
            return
        self.has_sys_status = True
        self.sensors_present = msg.onboard_control_sensors_present
        self.sensors_enabled = msg.onboard_control_sensors_enabled
        self.sensors_health = msg.onboard_control_sensors_health
        self.battery_pct = msg.battery_remaining

    def on_gps_raw_int(self, msg: mavlink.MAVLink_gps_raw_int_message) -> None:
        if msg.get_srcComponent() == AUTOPILOT_COMPONENT_ID:
            self.gps_fix_type = msg.fix_type

    def on_mission_request_int(self, msg: mavlink.MAVLink_mission_request_int_message) -> None:
        self.mission_requests.append((msg.seq, msg.mission_type))

    def on_mission_request(self, msg: mavlink.MAVLink_mission_request_message) -> None:
        self.mission_requests.append((msg.seq, msg.mission_type))  # legacy, answered with _INT

    def on_mission_ack(self, msg: mavlink.MAVLink_mission_ack_message) -> None:
        self.mission_ack = (msg.type, msg.mission_type)


_HANDLERS: dict[str, Callable[[VehicleState, mavlink.MAVLink_message], None]] = {
    "PARAM_VALUE": VehicleState.on_param_value,
    "HEARTBEAT": VehicleState.on_heartbeat,
    "GLOBAL_POSITION_INT": VehicleState.on_global_position_int,
    "HOME_POSITION": VehicleState.on_home_position,
    "STATUSTEXT": VehicleState.on_statustext,
    "EXTENDED_SYS_STATE": VehicleState.on_extended_sys_state,
    "SYSTEM_TIME": VehicleState.on_system_time,
    "COMMAND_ACK": VehicleState.on_command_ack,
    "CAMERA_IMAGE_CAPTURED": VehicleState.on_camera_image_captured,
    "MISSION_REQUEST_INT": VehicleState.on_mission_request_int,
    "MISSION_REQUEST": VehicleState.on_mission_request,
    "MISSION_ACK": VehicleState.on_mission_ack,
    "SYS_STATUS": VehicleState.on_sys_status,
    "GPS_RAW_INT": VehicleState.on_gps_raw_int,
}
