"""The parameter set of a simulated ArduPlane, served over the MAVLink parameter protocol.

Names, types and meanings follow ArduPlane 4.5 where a parameter exists there; defaults follow
ArduPlane except where the simulated airframe (a 100 m/s plane of the paper) or the simulator's
job needs otherwise, marked "sim" below and listed in docs/simulator.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

INT8 = mavlink.MAV_PARAM_TYPE_INT8
INT16 = mavlink.MAV_PARAM_TYPE_INT16
INT32 = mavlink.MAV_PARAM_TYPE_INT32
REAL32 = mavlink.MAV_PARAM_TYPE_REAL32


@dataclass(frozen=True)
class ParameterSpec:
    """One parameter: MAVLink type, default, accepted range and whether a GCS may change it."""

    name: str
    ptype: int
    default: float
    low: float
    high: float
    writable: bool = True
    doc: str = ""


def default_specs(sysid: int, airspeed_mps: float, altitude_m: float) -> tuple[ParameterSpec, ...]:
    """The parameters of vehicle ``sysid`` flying at ``airspeed_mps`` and ``altitude_m``."""
    p = ParameterSpec
    return (
        p(
            "SYSID_THISMAV",
            INT16,
            sysid,
            1,
            255,
            False,
            "this vehicle's system id (fixed: index + 1)",
        ),
        p("SYSID_MYGCS", INT16, 255, 1, 255, True, "ground station system id"),
        p("AIRSPEED_CRUISE", REAL32, airspeed_mps, 5, 400, True, "sim: cruise airspeed, m/s"),
        p("AIRSPEED_MIN", INT16, max(5, round(airspeed_mps * 0.6)), 5, 400, True, "m/s"),
        # 1.5 x cruise: the paper's grid flies a diagonal cell (1.41 km) in one 10 s step
        p("AIRSPEED_MAX", INT16, round(airspeed_mps * 1.5), 5, 400, True, "m/s"),
        p("ROLL_LIMIT_DEG", REAL32, 45, 10, 89, True, "bank limit, deg (sets the turn rate)"),
        p("TECS_CLMB_MAX", REAL32, 5, 0.1, 50, True, "max climb rate, m/s"),
        p("TECS_SINK_MAX", REAL32, 5, 0.1, 50, True, "max sink rate, m/s"),
        p("WP_RADIUS", INT16, 90, 1, 32767, True, "waypoint acceptance radius, m"),
        p("WP_LOITER_RAD", INT16, 60, -32767, 32767, True, "loiter radius, m (<0: CCW)"),
        p("RTL_RADIUS", INT16, 0, -32767, 32767, True, "RTL loiter radius, m (0: WP_LOITER_RAD)"),
        p("RTL_ALTITUDE", REAL32, altitude_m, -1, 32000, True, "sim: RTL altitude, m (-1: keep)"),
        p("TKOFF_ALT", REAL32, altitude_m, 0, 32000, True, "sim: take-off altitude, m"),
        # GCS failsafe as ArduPlane (sim_gateway/failsafe.py), ArduPlane's defaults: off until a
        # ground station turns it on (the planner daemon does,
        # mavlink_bridge/vehicles/gcs_failsafe.py)
        p("FS_GCS_ENABL", INT8, 0, 0, 3, True, "0 off, 1 heartbeat, 2 hb+RSSI, 3 hb in AUTO"),
        p("FS_SHORT_TIMEOUT", REAL32, 1.5, 1, 100, True, "s; RC failsafe only (no RC here)"),
        p("FS_LONG_TIMEOUT", REAL32, 5.0, 1, 300, True, "s (wall clock) without GCS to act"),
        p("FS_SHORT_ACTN", INT8, 0, 0, 4, True, "RC failsafe only (no RC here)"),
        p("FS_LONG_ACTN", INT8, 0, 0, 5, True, "0 continue, 1 RTL, 2 glide, 4 AUTO"),
        p("FENCE_ENABLE", INT8, 1, 0, 1, True, "sim: fence enforced (ArduPlane default 0)"),
        p("FENCE_ACTION", INT8, 1, 0, 6, True, "breach action: 0 report only, 1 RTL, else loiter"),
        p("ARMING_CHECK", INT32, 1, 0, 2**31 - 1, True, "pre-arm checks (the boot phase)"),
        p("BATT_CAPACITY", INT32, 0, 0, 2**31 - 1, False, "sim: range is tracked in km instead"),
    )


class ParameterSet:
    """Current values of one vehicle's parameters, in a fixed order (PARAM_VALUE index)."""

    def __init__(self, specs: tuple[ParameterSpec, ...]) -> None:
        self._specs = {s.name: s for s in specs}
        self._order = [s.name for s in specs]
        self._values = {s.name: float(s.default) for s in specs}

    def __len__(self) -> int:
        return len(self._order)

    def __contains__(self, name: str) -> bool:
        return name in self._specs

    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def names(self) -> list[str]:
        return list(self._order)

    def index(self, name: str) -> int:
        return self._order.index(name)

    def name_at(self, index: int) -> str | None:
        return self._order[index] if 0 <= index < len(self._order) else None

    def ptype(self, name: str) -> int:
        return self._specs[name].ptype

    def set(self, name: str, value: float) -> str | None:
        """Set a parameter; returns None when accepted, else the reason it was refused."""
        spec = self._specs.get(name)
        if spec is None:
            return f"unknown parameter {name}"
        if not spec.writable:
            return f"{name} is read-only in the simulator"
        if not math.isfinite(value) or not spec.low <= value <= spec.high:
            return f"{name} must be in [{spec.low:g}, {spec.high:g}]"
        if spec.ptype != REAL32:
            value = float(round(value))
        self._values[name] = float(value)
        return None
