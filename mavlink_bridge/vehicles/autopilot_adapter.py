"""What differs between the autopilots the daemon flies: ArduPilot (ArduPlane) and PX4.

Chosen per vehicle by its HEARTBEAT's ``autopilot`` field (:func:`autopilot_for`: PX4 by
``MAV_AUTOPILOT_PX4``, every other value ArduPilot, whose behaviour the project's simulator
copies). The daemon asks the adapter, never the autopilot field:

=====================  ===============================  ========================================
                       ArduPilot (ArduPlane)            PX4 (fixed wing)
=====================  ===============================  ========================================
take-off               DO_SET_MODE TAKEOFF (to          NAV_TAKEOFF, param7 = AMSL altitude
                       TKOFF_ALT)                       (runway take-off, then AUTO.LOITER)
guided flight          GUIDED; DO_REPOSITION, frame     AUTO.LOITER (PX4 has no GUIDED);
                       GLOBAL_RELATIVE_ALT              DO_REPOSITION, frame GLOBAL: PX4 reads
                                                        z as AMSL whatever the frame (measured:
                                                        z = 70 relative sent it into the ground)
"left guided"          mode is not GUIDED               mode is not AUTO.LOITER
tracked as flown       GUIDED or TAKEOFF                AUTO.LOITER or AUTO.TAKEOFF
RTL                    DO_SET_MODE RTL; mode RTL        NAV_RETURN_TO_LAUNCH; mode AUTO.RTL
mode names             custom_mode = mode number        custom_mode = sub << 24 | main << 16
GCS-loss settings      FS_SHORT_ACTN 0, FS_LONG_ACTN    NAV_DLL_ACT 0 (no action: circle the
                       0, FS_LONG_TIMEOUT 5,            last target), COM_DL_LOSS_T 5, GF_ACTION
                       FS_GCS_ENABL 1                   2 (hold), GF_PREDICT 1 (act before entry)
integer parameters     the value as a float             the bytes of an int32
                                                        (``param_encoding.py``)
airframe parameters    AIRSPEED_*, ROLL_LIMIT_DEG,      FW_AIRSPD_MIN/TRIM/MAX, FW_R_LIM,
                       WP_LOITER_RAD, WP_RADIUS         NAV_LOITER_RAD, NAV_ACC_RAD
airspeed cap           none: AIRSPEED_MAX is flown      the measured top airspeed of a known
                                                        airframe (SYS_AUTOSTART) caps
                                                        FW_AIRSPD_TRIM/MAX (``fly_limits``)
=====================  ===============================  ========================================

Readiness (SYS_STATUS pre-arm bit, GPS fix, home), arming, the fence upload (circle exclusions),
DO_CHANGE_SPEED and the camera's capture are the same for both (``readiness.py``,
``fence_upload.py``, ``guided_commands.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from mavlink_bridge.vehicles.guided_commands import Command, reposition_command, set_mode_command
from mavlink_wire.protocol import (
    PLANE_MODE_GUIDED,
    PLANE_MODE_RTL,
    PLANE_MODE_TAKEOFF,
    mavlink,
    mode_name,
)

if TYPE_CHECKING:
    from mavlink_bridge.vehicles.vehicle_state import VehicleState

INT8 = mavlink.MAV_PARAM_TYPE_INT8
INT32 = mavlink.MAV_PARAM_TYPE_INT32
REAL32 = mavlink.MAV_PARAM_TYPE_REAL32

#: (name, value, MAVLink type) of a parameter to set
Parameter = tuple[str, float, int]


@dataclass(frozen=True)
class GcsFailsafeSettings:
    """ArduPlane's GCS failsafe parameters, as the daemon sets them (``gcs_failsafe.py``)."""

    enable: int = 1  # FS_GCS_ENABL: 1 = heartbeat
    long_timeout_s: float = 5.0  # FS_LONG_TIMEOUT (ArduPlane's default)
    short_action: int = 0  # FS_SHORT_ACTN: RC loss in GUIDED: no change
    long_action: int = 0  # FS_LONG_ACTN: 0 = Continue (GUIDED circles its last target)

    def parameters(self) -> tuple[tuple[str, float, int], ...]:
        """(name, value, MAVLink type) of every parameter to set."""
        return (
            ("FS_SHORT_ACTN", float(self.short_action), INT8),
            ("FS_LONG_ACTN", float(self.long_action), INT8),
            ("FS_LONG_TIMEOUT", float(self.long_timeout_s), REAL32),
            ("FS_GCS_ENABL", float(self.enable), INT8),  # last: on once the actions are right
        )


MISSION_FAILSAFE = GcsFailsafeSettings()


#: PX4 airframes (SYS_AUTOSTART) that cannot fly the FW_AIRSPD_MAX they report, with the top
#: airspeed (m/s, indicated) measured in level flight at full throttle: the SIH airplane
#: (10041, PX4 SITL) reports FW_AIRSPD_TRIM 15 and MAX 20 but flies 13.6 m/s at 100 % throttle
#: when asked for 20, 12.9 asked for 15 (benchmarks/px4_sih_flight.py, docs/px4.md). Only an
#: airframe listed here is capped; every other one's parameters are believed.
PX4_TOP_AIRSPEED_MPS: dict[int, float] = {10041: 13.5}

# PX4's custom_mode: main mode in bits 16..23, sub mode (of AUTO) in bits 24..31
PX4_MAIN_AUTO = 4
PX4_AUTO_TAKEOFF, PX4_AUTO_LOITER, PX4_AUTO_RTL = 2, 3, 5
PX4_MAIN_NAMES = {
    1: "MANUAL",
    2: "ALTCTL",
    3: "POSCTL",
    4: "AUTO",
    5: "ACRO",
    6: "OFFBOARD",
    7: "STABILIZED",
    8: "RATTITUDE",
}
PX4_AUTO_NAMES = {
    1: "READY",
    2: "TAKEOFF",
    3: "LOITER",
    4: "MISSION",
    5: "RTL",
    6: "LAND",
    8: "FOLLOW_TARGET",
    9: "PRECLAND",
}


def px4_custom_mode(main: int, sub: int = 0) -> int:
    """PX4's HEARTBEAT custom_mode for a main mode and (AUTO) sub mode."""
    return (sub << 24) | (main << 16)


def px4_mode_name(custom_mode: int) -> str:
    """``AUTO.LOITER``, ``AUTO.RTL``, ``POSCTL``...; ``mode N`` for an unknown one."""
    main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
    name = PX4_MAIN_NAMES.get(main)
    if name is None:
        return f"mode {custom_mode}"
    if main == PX4_MAIN_AUTO:
        return f"AUTO.{PX4_AUTO_NAMES.get(sub, str(sub))}"
    return name


@dataclass(frozen=True)
class ArduPilot:
    """ArduPlane (and the project's simulator, which behaves as ArduPlane)."""

    name: str = "ArduPilot"
    guided_name: str = "GUIDED"
    #: what a vehicle that refuses the GCS-loss settings must be set to by hand
    failsafe_fix: str = "FS_GCS_ENABL 1, FS_LONG_ACTN 0"
    #: field -> the parameter names that may hold it, newest first, with the scale to SI units
    airframe_names: tuple[tuple[str, tuple[tuple[str, float], ...]], ...] = (
        ("min_airspeed_mps", (("AIRSPEED_MIN", 1.0), ("ARSPD_FBW_MIN", 1.0))),
        ("cruise_mps", (("AIRSPEED_CRUISE", 1.0), ("TRIM_ARSPD_CM", 0.01))),
        ("max_airspeed_mps", (("AIRSPEED_MAX", 1.0), ("ARSPD_FBW_MAX", 1.0))),
        ("bank_limit_deg", (("ROLL_LIMIT_DEG", 1.0), ("LIM_ROLL_CD", 0.01))),
        ("wp_loiter_radius_m", (("WP_LOITER_RAD", 1.0),)),
        ("capture_radius_m", (("WP_RADIUS", 1.0),)),
    )

    #: parameters read beside ``airframe_names`` for ``fly_limits``
    limit_names: tuple[str, ...] = ()

    def fly_limits(
        self, fields: dict[str, float], params: dict[str, float]
    ) -> tuple[dict[str, float], str]:
        """The airframe ``fields`` (``airframe.Airframe``'s) the autopilot can really fly, and
        a note saying what was capped ("" when nothing): ArduPilot flies its parameters."""
        return fields, ""

    def mode_name(self, custom_mode: int) -> str:
        return mode_name(custom_mode)

    def guided(self, custom_mode: int) -> bool:
        """In the mode the daemon flies it in."""
        return custom_mode == PLANE_MODE_GUIDED

    def flown(self, custom_mode: int) -> bool:
        """Guided or taking off (the track audit's "not a failsafe")."""
        return custom_mode in (PLANE_MODE_GUIDED, PLANE_MODE_TAKEOFF)

    def returning(self, custom_mode: int) -> bool:
        return custom_mode == PLANE_MODE_RTL

    def takeoff_command(self, vehicle: VehicleState, climb_m: float) -> Command:
        """TAKEOFF mode (it climbs to its own TKOFF_ALT)."""
        return set_mode_command(vehicle, PLANE_MODE_TAKEOFF)

    def guide_command(self, vehicle: VehicleState) -> Command:
        """Into the guided mode, once climbed."""
        return set_mode_command(vehicle, PLANE_MODE_GUIDED)

    def rtl_command(self, vehicle: VehicleState) -> Command:
        return set_mode_command(vehicle, PLANE_MODE_RTL)

    def reposition_command(
        self, vehicle: VehicleState, lat_deg: float, lon_deg: float, altitude_m: float
    ) -> Command:
        """Fly to lat/lon at ``altitude_m`` above home and circle there."""
        return reposition_command(vehicle, lat_deg, lon_deg, altitude_m)

    def failsafe_parameters(self) -> tuple[Parameter, ...]:
        """The GCS-loss settings (``gcs_failsafe.py``), the one that enables them last."""
        return MISSION_FAILSAFE.parameters()

    def failsafe_summary(self) -> str:
        s = MISSION_FAILSAFE
        return (
            f"FS_GCS_ENABL {s.enable}, FS_LONG_ACTN {s.long_action} (continue: circle the last "
            f"guided target), FS_LONG_TIMEOUT {s.long_timeout_s:g} s"
        )


@dataclass(frozen=True)
class PX4(ArduPilot):
    """PX4 fixed wing (measured with PX4 SITL's SIH airplane, ../shared/sitl/px4/README.md)."""

    name: str = "PX4"
    guided_name: str = "AUTO.LOITER"
    failsafe_fix: str = "NAV_DLL_ACT 0, GF_ACTION 2, GF_PREDICT 1"
    airframe_names: tuple[tuple[str, tuple[tuple[str, float], ...]], ...] = (
        ("min_airspeed_mps", (("FW_AIRSPD_MIN", 1.0),)),
        ("cruise_mps", (("FW_AIRSPD_TRIM", 1.0),)),
        ("max_airspeed_mps", (("FW_AIRSPD_MAX", 1.0),)),
        ("bank_limit_deg", (("FW_R_LIM", 1.0),)),
        ("wp_loiter_radius_m", (("NAV_LOITER_RAD", 1.0),)),
        ("capture_radius_m", (("NAV_ACC_RAD", 1.0),)),
    )
    #: NAV_DLL_ACT 0: a lost data link changes nothing, the plane circles its last target
    dll_action: int = 0
    dl_loss_timeout_s: int = 5  # COM_DL_LOSS_T: when the loss is reported
    fence_action: int = 2  # GF_ACTION 2: hold (loiter where it is)
    fence_predict: int = 1  # GF_PREDICT 1: act on a predicted breach, before the zone
    takeoff_margin_m: float = 10.0
    limit_names: tuple[str, ...] = ("SYS_AUTOSTART",)

    def fly_limits(
        self, fields: dict[str, float], params: dict[str, float]
    ) -> tuple[dict[str, float], str]:
        """Cruise and fastest airspeed no higher than the airframe's measured top speed when
        its SYS_AUTOSTART is in ``PX4_TOP_AIRSPEED_MPS`` (the slowest no higher either)."""
        top = PX4_TOP_AIRSPEED_MPS.get(round(params.get("SYS_AUTOSTART", -1)))
        if top is None or fields["max_airspeed_mps"] <= top:
            return fields, ""
        capped = {**fields}
        for key in ("min_airspeed_mps", "cruise_mps", "max_airspeed_mps"):
            capped[key] = min(fields[key], top)
        note = (
            f"FW_AIRSPD_MAX {fields['max_airspeed_mps']:g} capped to {top:g} m/s, the measured "
            f"top speed of airframe {round(params['SYS_AUTOSTART'])}"
        )
        return capped, note

    def mode_name(self, custom_mode: int) -> str:
        return px4_mode_name(custom_mode)

    def guided(self, custom_mode: int) -> bool:
        return custom_mode == px4_custom_mode(PX4_MAIN_AUTO, PX4_AUTO_LOITER)

    def flown(self, custom_mode: int) -> bool:
        return self.guided(custom_mode) or custom_mode == px4_custom_mode(
            PX4_MAIN_AUTO, PX4_AUTO_TAKEOFF
        )

    def returning(self, custom_mode: int) -> bool:
        return custom_mode == px4_custom_mode(PX4_MAIN_AUTO, PX4_AUTO_RTL)

    def takeoff_command(self, vehicle: VehicleState, climb_m: float) -> Command:
        """NAV_TAKEOFF to ``climb_m`` + ``takeoff_margin_m`` above home (param7 AMSL): a runway
        take-off, then AUTO.LOITER around the take-off point. The margin: PX4 levels off just
        under its take-off altitude (a take-off to the 30 m the daemon waits for never got there
        in 60 s of SITL)."""
        nan = math.nan
        alt = home_amsl_m(vehicle) + climb_m + self.takeoff_margin_m
        return Command(vehicle, mavlink.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, nan, nan, nan, alt))

    def guide_command(self, vehicle: VehicleState) -> Command:
        """DO_SET_MODE AUTO.LOITER (param2 main mode, param3 sub mode)."""
        flag = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        params = (flag, PX4_MAIN_AUTO, PX4_AUTO_LOITER, 0, 0, 0, 0)
        return Command(vehicle, mavlink.MAV_CMD_DO_SET_MODE, params)

    def rtl_command(self, vehicle: VehicleState) -> Command:
        return Command(vehicle, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH)

    def reposition_command(
        self, vehicle: VehicleState, lat_deg: float, lon_deg: float, altitude_m: float
    ) -> Command:
        """DO_REPOSITION in frame GLOBAL with the AMSL altitude (home + ``altitude_m``)."""
        cmd = reposition_command(vehicle, lat_deg, lon_deg, home_amsl_m(vehicle) + altitude_m)
        cmd.frame = mavlink.MAV_FRAME_GLOBAL_INT
        return cmd

    def failsafe_parameters(self) -> tuple[Parameter, ...]:
        return (
            ("NAV_DLL_ACT", float(self.dll_action), INT32),
            ("COM_DL_LOSS_T", float(self.dl_loss_timeout_s), INT32),
            ("GF_PREDICT", float(self.fence_predict), INT32),
            ("GF_ACTION", float(self.fence_action), INT32),
        )

    def failsafe_summary(self) -> str:
        return (
            f"NAV_DLL_ACT {self.dll_action} (no action: circle the last target), COM_DL_LOSS_T "
            f"{self.dl_loss_timeout_s} s, GF_ACTION {self.fence_action} (hold), GF_PREDICT "
            f"{self.fence_predict}"
        )


#: the commands an adapter's ``rtl_command`` sends (the flight home tells RTL from a reposition)
RTL_COMMANDS = frozenset({mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH})

ARDUPILOT = ArduPilot()
PX4_AUTOPILOT = PX4()


def autopilot_for(vehicle: VehicleState) -> ArduPilot:
    """The vehicle's autopilot adapter, by its HEARTBEAT (PX4, else ArduPilot)."""
    return adapter_for_autopilot(vehicle.autopilot)


def adapter_for_autopilot(autopilot: int) -> ArduPilot:
    """The adapter for a HEARTBEAT autopilot value."""
    return PX4_AUTOPILOT if autopilot == mavlink.MAV_AUTOPILOT_PX4 else ARDUPILOT


def home_amsl_m(vehicle: VehicleState) -> float:
    """The vehicle's home altitude above mean sea level: HOME_POSITION's, else its position's
    AMSL altitude less its height above home."""
    if vehicle.home is not None:
        return vehicle.home[2]
    return vehicle.alt_amsl_m - vehicle.relative_alt_m
