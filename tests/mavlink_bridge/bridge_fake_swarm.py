"""A minimal stand-in swarm for the daemon's tests: N vehicles, each its own UDP socket sending
to the daemon (like SITL's udpout), speaking just enough ArduPlane: heartbeats with an
initialising phase, GLOBAL_POSITION_INT, HOME_POSITION on request, fence upload, PARAM_SET
(echoed), PARAM_REQUEST_READ of its airframe limits, arm (refusable with a PreArm STATUSTEXT),
mode changes (RTL flies home), COMMAND_INT DO_REPOSITION (COMMAND_LONG answered UNSUPPORTED),
DO_CHANGE_SPEED within 60..150 m/s, sensor looks and engagement captures from the camera
component. Flies straight to each target at the commanded speed. For protocol tests only; the
end-to-end tests use ``swarmplan sim``."""

from __future__ import annotations

import math
import os
import socket
import threading
import time
from dataclasses import dataclass, field

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

M_PER_DEG = 111_320.0


@dataclass
class FakeVehicle:
    sysid: int
    lat: float
    lon: float
    daemon: tuple[str, int]
    speedup: float = 50.0
    init_s: float = 2.0  # simulated seconds in CALIBRATING
    refuse_arm: str | None = None  # PreArm text to refuse arming with
    refuse_command: int | None = None  # a command id answered DENIED
    keep_param: str | None = None  # a parameter a PARAM_SET does not change (echoes its old 0)
    params_after_s: float = 0.0  # PARAM_REQUEST_READ unanswered this long (wall s; still booting)
    silent: threading.Event = field(default_factory=threading.Event)
    sock: socket.socket = field(
        default_factory=lambda: socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    )
    mode: int = 0
    armed: bool = False
    alt: float = 0.0
    target: tuple[float, float] | None = None
    fence_items: list = field(default_factory=list)
    mission_items: list = field(default_factory=list)
    upload_count: dict = field(default_factory=dict)
    #: the first fence upload as a duplicating, delaying link plays it: after item 1 a late
    #: MISSION_COUNT restarts the transfer (it asks for item 0 again), a delayed item 1 completes
    #: it with the next item 0, its MISSION_ACK is lost, and the vehicle, its transfer over,
    #: ignores items until a new MISSION_COUNT
    fence_race: bool = False
    race_stage: int = 0
    look_index: int = 0
    engagement_seq: set = field(default_factory=set)
    commands: list = field(default_factory=list)
    speeds: list = field(default_factory=list)  # every accepted DO_CHANGE_SPEED, m/s
    airspeed: float = 150.0
    params: dict = field(default_factory=dict)  # every PARAM_SET received, by name
    #: what PARAM_REQUEST_READ answers (ArduPlane's names; the simulator's airframe)
    limits: dict = field(
        default_factory=lambda: {
            "AIRSPEED_MIN": 60.0, "AIRSPEED_CRUISE": 100.0, "AIRSPEED_MAX": 150.0,
            "ROLL_LIMIT_DEG": 45.0, "WP_LOITER_RAD": 60.0, "WP_RADIUS": 90.0,
        }
    )  # fmt: skip

    def __post_init__(self) -> None:
        self.home = (self.lat, self.lon)  # where it starts: its launch point
        self.created = time.monotonic()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.ap = mavlink.MAVLink(None, self.sysid, 1)
        self.cam = mavlink.MAVLink(None, self.sysid, 100)

    def send(self, mav: mavlink.MAVLink, msg: mavlink.MAVLink_message) -> None:
        if self.silent.is_set():
            return
        try:
            self.sock.sendto(msg.pack(mav), self.daemon)
            mav.seq = (mav.seq + 1) % 256
        except OSError:
            pass


class FakeSwarm(threading.Thread):
    """N fake vehicles on one thread; ``stop()`` ends it."""

    def __init__(
        self,
        n: int,
        daemon_port: int,
        lat0: float = -35.36,
        lon0: float = 149.17,
        speedup: float = 50.0,
        camera: bool = True,  # False: no sensor looks (an autopilot without a payload)
        **vehicle_kwargs: object,
    ) -> None:
        super().__init__(daemon=True)
        self.speedup = speedup
        self.camera = camera
        self.vehicles = [
            FakeVehicle(
                i + 1,
                lat0 + 0.05 + 0.02 * i,
                lon0 + 0.05 + 0.02 * i,
                ("127.0.0.1", daemon_port),
                speedup,
                **vehicle_kwargs,
            )  # type: ignore[arg-type]
            for i in range(n)
        ]
        self._halt = threading.Event()
        self.sim_s = 0.0

    def stop(self) -> None:
        self._halt.set()
        self.join(5)
        for v in self.vehicles:
            v.sock.close()

    def run(self) -> None:
        last = time.monotonic()
        next_hb = 0.0
        next_look = 10.0
        while not self._halt.is_set():
            time.sleep(0.002)
            now = time.monotonic()
            dt = (now - last) * self.speedup
            last = now
            self.sim_s += dt
            for v in self.vehicles:
                self._receive(v)
                self._fly(v, dt)
            if now >= next_hb:
                next_hb = now + 0.05
                for v in self.vehicles:
                    self._telemetry(v)
            if self.camera and self.sim_s >= next_look:
                next_look += 10.0
                for v in self.vehicles:
                    if v.armed:
                        v.look_index += 1
                        v.send(
                            v.cam,
                            v.cam.camera_image_captured_encode(
                                int(self.sim_s * 1000),
                                0,
                                0,
                                int(v.lat * 1e7),
                                int(v.lon * 1e7),
                                0,
                                0,
                                [1, 0, 0, 0],
                                v.look_index,
                                1,
                                b"look:",
                            ),
                        )

    def _telemetry(self, v: FakeVehicle) -> None:
        status = (
            mavlink.MAV_STATE_CALIBRATING if self.sim_s < v.init_s else mavlink.MAV_STATE_STANDBY
        )
        if v.armed:
            status = mavlink.MAV_STATE_ACTIVE
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
            mavlink.MAV_MODE_FLAG_SAFETY_ARMED if v.armed else 0
        )
        v.send(
            v.ap,
            v.ap.heartbeat_encode(
                mavlink.MAV_TYPE_FIXED_WING,
                mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                base,
                v.mode,
                status,
            ),
        )
        v.send(
            v.ap,
            v.ap.global_position_int_encode(
                int(self.sim_s * 1000),
                int(v.lat * 1e7),
                int(v.lon * 1e7),
                int(v.alt * 1000),
                int(v.alt * 1000),
                0,
                0,
                0,
                0,
            ),
        )

    def _fly(self, v: FakeVehicle, dt: float) -> None:
        if v.armed and v.mode in (13, 15) and v.alt < 500:
            v.alt = min(500.0, v.alt + 10 * dt)
        goal = v.home if v.mode == 11 else v.target  # RTL: back to its launch point
        if goal is not None and v.mode in (11, 15):
            dn = (goal[0] - v.lat) * M_PER_DEG
            de = (goal[1] - v.lon) * M_PER_DEG * math.cos(math.radians(v.lat))
            d = math.hypot(dn, de)
            step = min(d, v.airspeed * dt)
            if d > 0:
                v.lat += dn / d * step / M_PER_DEG
                v.lon += de / d * step / (M_PER_DEG * math.cos(math.radians(v.lat)))

    def _ack(
        self,
        v: FakeVehicle,
        mav: mavlink.MAVLink,
        command: int,
        result: int,
        p2: int = 0,
        progress: int = 0,
    ) -> None:
        v.send(mav, mav.command_ack_encode(command, result, progress, p2, 255, 190))

    def _receive(self, v: FakeVehicle) -> None:
        while True:
            try:
                data = v.sock.recv(65535)
            except (BlockingIOError, OSError):
                return
            if v.silent.is_set():
                continue
            for msg in mavlink.MAVLink(None).parse_buffer(data) or ():
                self._handle(v, msg)

    def _handle(self, v: FakeVehicle, msg: mavlink.MAVLink_message) -> None:
        kind = msg.get_type()
        if kind == "COMMAND_LONG":
            v.commands.append(msg.command)
            if msg.command == v.refuse_command:
                self._ack(v, v.ap, msg.command, mavlink.MAV_RESULT_DENIED)
            elif msg.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                if v.refuse_arm or self.sim_s < v.init_s:
                    v.send(
                        v.ap,
                        v.ap.statustext_encode(
                            3, (v.refuse_arm or "PreArm: EKF not ready").encode()
                        ),
                    )
                    self._ack(v, v.ap, msg.command, mavlink.MAV_RESULT_FAILED)
                else:
                    v.armed = True
                    self._ack(v, v.ap, msg.command, mavlink.MAV_RESULT_ACCEPTED)
            elif msg.command == mavlink.MAV_CMD_DO_CHANGE_SPEED:
                ok = 60 <= msg.param2 <= 150
                if ok:
                    v.airspeed = msg.param2
                    v.speeds.append(msg.param2)
                result = mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_DENIED
                self._ack(v, v.ap, msg.command, result)
            elif msg.command == mavlink.MAV_CMD_DO_SET_MODE:
                v.mode = int(msg.param2)
                self._ack(v, v.ap, msg.command, mavlink.MAV_RESULT_ACCEPTED)
            elif msg.command == mavlink.MAV_CMD_IMAGE_START_CAPTURE and msg.target_component == 100:
                v.engagement_seq.add(int(msg.param4))
                # the camera echoes the sequence number (low byte) in result_param1
                self._ack(
                    v, v.cam, msg.command, mavlink.MAV_RESULT_ACCEPTED, 0, int(msg.param4) % 256
                )
            elif (
                msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE
                and int(msg.param1) == mavlink.MAVLINK_MSG_ID_HOME_POSITION
            ):
                self._ack(v, v.ap, msg.command, mavlink.MAV_RESULT_ACCEPTED)
                lat, lon = round(v.home[0] * 1e7), round(v.home[1] * 1e7)
                v.send(
                    v.ap,
                    v.ap.home_position_encode(lat, lon, 584000, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0),
                )
            else:
                self._ack(v, v.ap, msg.command, mavlink.MAV_RESULT_UNSUPPORTED)
        elif kind == "COMMAND_INT":
            v.commands.append(msg.command)
            if msg.command == v.refuse_command:
                self._ack(v, v.ap, msg.command, mavlink.MAV_RESULT_DENIED)
            elif msg.command == mavlink.MAV_CMD_DO_REPOSITION:
                v.target = (msg.x * 1e-7, msg.y * 1e-7)
                if int(msg.param2) & 1:
                    v.mode = 15
                self._ack(v, v.ap, msg.command, mavlink.MAV_RESULT_ACCEPTED)
            else:
                self._ack(v, v.ap, msg.command, mavlink.MAV_RESULT_UNSUPPORTED)
        elif kind == "PARAM_SET":  # accepted and echoed (the GCS failsafe), but keep_param
            if msg.param_id != v.keep_param:
                v.params[msg.param_id] = msg.param_value
            value = v.params.get(msg.param_id, 0.0)
            v.send(v.ap, v.ap.param_value_encode(msg.param_id.encode(), value,
                                                 msg.param_type, 0, 0))  # fmt: skip
        elif kind == "PARAM_REQUEST_READ":  # by name; a name it does not have: no answer
            name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode()
            value = v.params.get(name, v.limits.get(name))
            if value is not None and time.monotonic() - v.created >= v.params_after_s:
                real32 = mavlink.MAV_PARAM_TYPE_REAL32
                v.send(v.ap, v.ap.param_value_encode(name.encode(), value, real32, 0, 0))
        elif kind == "MISSION_COUNT":
            items = v.fence_items if msg.mission_type == 1 else v.mission_items
            items.clear()
            if v.race_stage == 2:
                v.race_stage = 3  # a new upload: played straight from now on
            v.upload_count[msg.mission_type] = msg.count
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            if msg.count == 0:
                v.send(v.ap, v.ap.mission_ack_encode(*src, 0, msg.mission_type))
            else:
                v.send(v.ap, v.ap.mission_request_encode(*src, 0, msg.mission_type))
        elif kind in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            items = v.fence_items if msg.mission_type == 1 else v.mission_items
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            racing = v.fence_race and msg.mission_type == 1 and v.race_stage < 3
            if racing and v.race_stage == 2:
                return  # its transfer is over: items are ignored
            if racing and v.race_stage == 0 and msg.seq == 1:
                items.clear()  # a late MISSION_COUNT restarted it: item 0 again
                v.race_stage = 1
                v.send(v.ap, v.ap.mission_request_encode(*src, 0, msg.mission_type))
                return
            if racing and v.race_stage == 1 and msg.seq == 0:
                v.race_stage = 2  # the delayed item 1 completes it; the ACK is lost
                return
            if msg.seq == len(items):
                items.append(msg)
            if len(items) < v.upload_count.get(msg.mission_type, 0):
                v.send(v.ap, v.ap.mission_request_encode(*src, len(items), msg.mission_type))
            else:
                v.send(v.ap, v.ap.mission_ack_encode(*src, 0, msg.mission_type))
