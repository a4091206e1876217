"""One simulated ArduPlane: its state (armed, mode, home, boot phase, guided target, mission
progress) and its autopilot logic (mode changes, take-off, RTL, failsafe and fence actions;
flying AUTO missions is :class:`~sim_gateway.auto_mission.AutoMission`). Its motion lives in
the fleet's :class:`~sim_gateway.fixed_wing.FleetKinematics` (row ``index``); what it says and
hears over MAVLink lives in ``message_handlers``, ``commands``, ``mission_protocol``,
``parameter_protocol`` and ``telemetry``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from planner.engagement import EngagementOutcome
from planner.scenario import Origin
from sim_gateway import flight_modes as modes
from sim_gateway.auto_mission import AutoMission, MissionHost
from sim_gateway.camera import EngagementLog
from sim_gateway.failsafe import FailsafeEvent, GcsFailsafe, long_failsafe_mode
from sim_gateway.fixed_wing import FleetKinematics
from sim_gateway.geofence import exclusion_circles
from sim_gateway.mavlink_endpoint import (
    MAV_COMP_ID_AUTOPILOT1,
    MAV_COMP_ID_CAMERA,
    ComponentSender,
    LinkStats,
    VehicleSocket,
)
from sim_gateway.mission_store import FENCE, MissionStore
from sim_gateway.parameters import ParameterSet, default_specs
from sim_gateway.telemetry_streams import FleetSnapshot, StreamSchedule

BOOT_STATE_S = 1.0  # MAV_STATE_BOOT this long, then CALIBRATING until the boot phase ends


class VehicleHost(MissionHost, Protocol):
    """What a vehicle needs from the simulator that runs it."""

    stats: LinkStats
    origin: Origin
    decision_step: int
    boot_s: float

    def wall_s(self) -> float: ...
    def local_to_geodetic(self, x_m: float, y_m: float) -> tuple[float, float]: ...
    def engage(self, index: int) -> EngagementOutcome: ...
    def set_fence(self, index: int, circles: np.ndarray) -> None: ...
    def fence_circles(self, index: int) -> np.ndarray: ...
    def snapshot(self) -> FleetSnapshot: ...


@dataclass
class GuidedTarget:
    x_m: float
    y_m: float
    alt_m: float  # above home
    radius_m: float  # signed: < 0 counter-clockwise


class Vehicle(AutoMission):
    """State and autopilot behaviour of the plane in row ``index`` of the fleet."""

    def __init__(
        self,
        index: int,
        fleet: FleetKinematics,
        host: VehicleHost,
        sock: VehicleSocket,
        cruise_alt_m: float,
    ) -> None:
        self.index = index
        self.sysid = index + 1
        self.fleet = fleet
        self.host = host
        self.sock = sock
        self.autopilot = ComponentSender(self.sysid, MAV_COMP_ID_AUTOPILOT1)
        self.camera = ComponentSender(self.sysid, MAV_COMP_ID_CAMERA)
        self.params = ParameterSet(
            default_specs(self.sysid, float(fleet.airspeed_mps[index]), cruise_alt_m)
        )
        self.missions = MissionStore()
        self.failsafe = GcsFailsafe()
        self.engagements = EngagementLog()
        self.streams = StreamSchedule()
        self.armed = False
        self.mode = modes.MANUAL
        self.home_x_m = float(fleet.x_m[index])
        self.home_y_m = float(fleet.y_m[index])
        self.guided: GuidedTarget | None = None
        self.look_index = 0
        self.fence_breached = False
        self.range_exhausted = False
        self.item_wait_until_s: float | None = None  # AUTO loiter-time / turns deadline
        self.item_arrived = False
        self.jumps_left: dict[int, int] = {}
        #: per sender (sysid, compid): MAVLink sequence number and wall time of its newest
        #: command, so a command overtaken on the way (reordered) is not applied after it
        self.last_command: dict[tuple[int, int], tuple[int, float]] = {}
        self.apply_params()

    # ------------------------------------------------------------------ state

    @property
    def booting(self) -> bool:
        return self.host.sim_time_s < self.host.boot_s

    @property
    def airborne(self) -> bool:
        return bool(self.fleet.airborne[self.index])

    def system_status(self) -> int:
        if self.host.sim_time_s < min(BOOT_STATE_S, self.host.boot_s):
            return mavlink.MAV_STATE_BOOT
        if self.booting:
            return mavlink.MAV_STATE_CALIBRATING
        if self.failsafe.stage or self.fence_breached or self.range_exhausted:
            return mavlink.MAV_STATE_CRITICAL
        return mavlink.MAV_STATE_ACTIVE if self.armed else mavlink.MAV_STATE_STANDBY

    def base_mode(self) -> int:
        mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            mode |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if self.mode in (
            modes.AUTO,
            modes.RTL,
            modes.LOITER,
            modes.GUIDED,
            modes.CIRCLE,
            modes.TAKEOFF,
        ):
            mode |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        else:
            mode |= mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        return mode

    def apply_params(self, changed: str | None = None) -> None:
        """Push the flight parameters into the kinematics row (after a PARAM_SET of ``changed``:
        a speed commanded in flight stays unless AIRSPEED_CRUISE itself was set)."""
        i, p = self.index, self.params
        if changed in (None, "AIRSPEED_CRUISE"):
            self.fleet.set_airspeed(i, p["AIRSPEED_CRUISE"])
        self.fleet.bank_limit_rad[i] = math.radians(p["ROLL_LIMIT_DEG"])
        self.fleet.climb_mps[i] = p["TECS_CLMB_MAX"]
        self.fleet.sink_mps[i] = p["TECS_SINK_MAX"]

    # ------------------------------------------------------------------ sending

    def send(self, message: mavlink.MAVLink_message) -> None:
        self.sock.send(self.autopilot.pack(message))

    def send_from_camera(self, message: mavlink.MAVLink_message) -> None:
        self.sock.send(self.camera.pack(message))

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> None:
        self.send(mavlink.MAVLink_statustext_message(severity, text[:50].encode()))

    def ack(
        self,
        command: int,
        result: int,
        peer: tuple[int, int],
        progress: int = 0,
        result_param2: int = 0,
        from_camera: bool = False,
    ) -> None:
        """COMMAND_ACK to ``peer``, from the autopilot or (``from_camera``) the camera."""
        message = mavlink.MAVLink_command_ack_message(
            command,
            result,
            progress=progress,
            result_param2=result_param2,
            target_system=peer[0],
            target_component=peer[1],
        )
        if from_camera:
            self.send_from_camera(message)
        else:
            self.send(message)

    # ------------------------------------------------------------------ arming

    def prearm_failure(self) -> str | None:
        """Why the pre-arm checks fail now (ArduPlane's ``PreArm: ...``); None: it could arm.
        Arming refuses with it, and SYS_STATUS reports it (the PREARM_CHECK health bit)."""
        if self.booting and self.params["ARMING_CHECK"]:
            return "PreArm: AHRS: waiting for home"
        if self.range_exhausted:
            return "PreArm: Battery 1 below minimum arming capacity"
        return None

    def arm(self) -> tuple[int, str | None]:
        """Arm; returns (MAV_RESULT, reason refused)."""
        failure = self.prearm_failure()
        if failure is not None:
            return mavlink.MAV_RESULT_FAILED, failure
        if not self.armed:
            self.armed = True
            self.statustext("Arming motors")
            self.start_takeoff_if_due()
        return mavlink.MAV_RESULT_ACCEPTED, None

    def disarm(self, force: bool) -> tuple[int, str | None]:
        if self.airborne and not force:
            return mavlink.MAV_RESULT_FAILED, "Disarm refused: flying (use force)"
        if self.airborne:
            self.land_now()
        self.armed = False
        return mavlink.MAV_RESULT_ACCEPTED, None

    def land_now(self) -> None:
        i = self.index
        self.fleet.airborne[i] = False
        self.fleet.alt_m[i] = 0.0
        self.fleet.target_alt_m[i] = 0.0
        self.fleet.hold_course(i)

    # ------------------------------------------------------------------ modes

    def set_mode(self, mode: int, reason: str = "") -> bool:
        """Change flight mode; False when the mode is unknown or cannot be entered now."""
        if mode not in modes.SUPPORTED_MODES:
            return False
        if mode == modes.AUTO and len(self.missions.mission()) < 2:
            self.statustext("Mode change to AUTO failed: no mission", mavlink.MAV_SEVERITY_WARNING)
            return False
        i, fleet, p = self.index, self.fleet, self.params
        if mode != self.mode:
            # a new mode drops a speed commanded with DO_CHANGE_SPEED: back to cruise
            # (ArduPlane's Mode::enter resets new_airspeed_cm; the same mode is not re-entered).
            # Kept, a plane sent 150 m/s for its last leg flew RTL at 150 m/s and circled
            # home on a 2.3 km turn radius, into a threat 4.2 km from its home
            fleet.set_airspeed(i, p["AIRSPEED_CRUISE"])
        self.mode = mode
        self.item_wait_until_s = None
        here = (float(fleet.x_m[i]), float(fleet.y_m[i]))
        if mode in modes.HOLD_COURSE_MODES:
            fleet.hold_course(i)
        elif mode in (modes.CIRCLE, modes.LOITER):
            fleet.orbit(i, *here, p["WP_LOITER_RAD"])
        elif mode == modes.GUIDED:
            if self.guided is None:
                self.guided = GuidedTarget(*here, float(fleet.target_alt_m[i]), p["WP_LOITER_RAD"])
                fleet.orbit(i, *here, p["WP_LOITER_RAD"])
            else:
                self.fly_to_guided()
        elif mode == modes.RTL:
            self.return_to_launch()
        elif mode == modes.AUTO:
            seq = max(self.missions.current_seq, 1)
            self.start_mission_item(seq)
        elif mode == modes.TAKEOFF:
            if self.airborne:
                fleet.target_alt_m[i] = max(p["TKOFF_ALT"], float(fleet.alt_m[i]))
                fleet.orbit(i, *here, p["WP_LOITER_RAD"])
            else:
                self.start_takeoff_if_due()
        if reason:
            self.statustext(f"{reason}: mode {modes.mode_name(mode)}", mavlink.MAV_SEVERITY_WARNING)
        return True

    def return_to_launch(self) -> None:
        i, p = self.index, self.params
        radius = p["RTL_RADIUS"] or p["WP_LOITER_RAD"]
        self.fleet.fly_to(i, self.home_x_m, self.home_y_m, p["WP_RADIUS"], radius)
        if p["RTL_ALTITUDE"] >= 0 and self.airborne:
            self.fleet.target_alt_m[i] = p["RTL_ALTITUDE"]

    def start_takeoff_if_due(self) -> None:
        """Leave the ground when armed in TAKEOFF mode or in AUTO at a NAV_TAKEOFF item."""
        if not self.armed or self.airborne:
            return
        i, fleet = self.index, self.fleet
        if self.mode == modes.TAKEOFF:
            alt = self.params["TKOFF_ALT"]
        elif self.mode == modes.AUTO and self.current_item_command() == mavlink.MAV_CMD_NAV_TAKEOFF:
            alt = self.item_relative_alt(self.missions.mission()[self.missions.current_seq])
        else:
            return
        fleet.airborne[i] = True
        fleet.hold_course(i)
        fleet.target_alt_m[i] = max(alt, 10.0)
        self.statustext(f"Takeoff to {alt:.0f} m")

    # ------------------------------------------------------------------ guided

    def set_guided_target(self, target: GuidedTarget) -> None:
        self.guided = target
        if self.mode == modes.GUIDED:
            self.fly_to_guided()

    def fly_to_guided(self) -> None:
        g, i = self.guided, self.index
        assert g is not None
        self.fleet.fly_to(i, g.x_m, g.y_m, self.params["WP_RADIUS"], g.radius_m)
        if self.airborne:
            self.fleet.target_alt_m[i] = g.alt_m

    # ------------------------------------------------------------------ fence, range, link

    def fence_items_changed(self) -> None:
        circles = exclusion_circles(self.missions.items[FENCE], self.host.origin)
        self.host.set_fence(self.index, circles)

    def on_fence_breach(self) -> None:
        """First tick inside an exclusion circle."""
        self.fence_breached = True
        self.statustext("Fence Breached", mavlink.MAV_SEVERITY_CRITICAL)
        action = int(self.params["FENCE_ACTION"])
        if not self.params["FENCE_ENABLE"] or action == 0:
            return
        if action == 1 and self.mode != modes.RTL:
            self.set_mode(modes.RTL, "Fence breach")
        elif action != 1 and self.mode not in (modes.RTL, modes.LOITER):
            self.set_mode(modes.LOITER, "Fence breach")

    def on_fence_clear(self) -> None:
        self.fence_breached = False

    def on_range_exhausted(self) -> None:
        self.range_exhausted = True
        self.statustext("Battery 1 is critical: range used up", mavlink.MAV_SEVERITY_CRITICAL)
        if self.mode != modes.RTL:
            self.set_mode(modes.RTL, "Battery failsafe")

    def on_gcs_heartbeat(self, now_wall_s: float) -> None:
        if self.failsafe.heard(now_wall_s) == FailsafeEvent.CLEARED:
            self.statustext("GCS Failsafe Cleared")  # the mode stays what the failsafe made it

    def check_failsafe(self, now_wall_s: float) -> None:
        """ArduPlane's GCS failsafe (sim_gateway/failsafe.py): after FS_LONG_TIMEOUT without a
        ground-station heartbeat, FS_LONG_ACTN in the current mode."""
        p = self.params
        event = self.failsafe.check(
            now_wall_s,
            int(p["FS_GCS_ENABL"]),
            self.armed and self.airborne,
            self.mode,
            p["FS_LONG_TIMEOUT"],
        )
        if event != FailsafeEvent.LONG:
            return
        new_mode = long_failsafe_mode(self.mode, int(p["FS_LONG_ACTN"]))
        self.statustext(
            f"GCS Failsafe On: {modes.mode_name(self.mode if new_mode is None else new_mode)}",
            mavlink.MAV_SEVERITY_CRITICAL,
        )
        if new_mode is not None:
            self.set_mode(new_mode)
