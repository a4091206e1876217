"""Fly the airframe you have: each vehicle's own flight limits, read at launch.

The daemon's plane model (``flight_prediction.PlaneModel``: turn radius, loiter circle, leg
timing) used to assume our simulator's 100 m/s plane. A real autopilot knows its airframe; the
daemon asks for it with PARAM_REQUEST_READ before take-off:

* slowest airspeed, m/s: ArduPlane AIRSPEED_MIN (before 4.5: ARSPD_FBW_MIN), PX4 FW_AIRSPD_MIN
* cruise airspeed, m/s: AIRSPEED_CRUISE (TRIM_ARSPD_CM / 100), FW_AIRSPD_TRIM
* fastest airspeed, m/s: AIRSPEED_MAX (ARSPD_FBW_MAX), FW_AIRSPD_MAX
* bank limit, deg: ROLL_LIMIT_DEG (LIM_ROLL_CD / 100), FW_R_LIM
* loiter radius, m: WP_LOITER_RAD, NAV_LOITER_RAD
* waypoint acceptance radius, m: WP_RADIUS, NAV_ACC_RAD

(The PX4 names are those of its fixed-wing position controller and navigator parameter files.)
The autopilot's adapter may then cap them to what the airframe really flies
(``autopilot_adapter.ArduPilot.fly_limits``: PX4 SITL's SIH airplane reports FW_AIRSPD_MAX 20 but
tops out at 13.6 m/s, so its cruise and fastest airspeed become 13.5 m/s).
A name the vehicle does not answer within the read window falls back to the daemon's own
assumption, and the airframe says so (``source``).

The fleet's plane model (vectorised over UAVs) holds the most restrictive of the vehicles'
limits (smallest bank limit, largest loiter and acceptance radii), which the safety margins and
the way home are judged with, and each plane's own turn where the fleet mixes airframes: the
flight envelope predicts every candidate path of a plane with that plane's bank limit, loiter
and acceptance radius (``PlaneModel.rows``). Leg airspeeds are each plane's own: every
plane's timed legs are clamped to its own airspeed range (``PlaneModel.uav_speed_ranges_mps``),
so a PX4 SIH plane is never asked above its 13.5 m/s while the ArduPlanes beside it still catch
up at up to 1.5 v. The turn radius at airspeed v is ``v**2 / (g tan(bank))`` (ArduPlane's
defaults: 22 m/s at 65 deg, 23 m; the loiter circle is then WP_LOITER_RAD, 80 m).

``scenario_warnings`` says, before take-off, when the scenario asks for what the airframe
cannot fly: a UAV speed outside its airspeed range, or grid legs (one cell per decision step,
a diagonal one sqrt(2) cells) faster than its fastest airspeed.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from mavlink_bridge.vehicles.autopilot_adapter import autopilot_for
from mavlink_bridge.vehicles.flight_prediction import PlaneModel
from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_wire.protocol import AUTOPILOT_COMPONENT_ID
from planner.config import PlannerConfig
from planner.errors import UserError

#: how long to wait for the answers, and how often to ask again for the missing ones (wall s)
READ_WINDOW_S = 4.0
RESEND_S = 0.5
#: ... and for a vehicle that has answered none yet: still starting (three PX4 SITL instances
#: at 5x on a loaded 2-core machine: one answered nothing in 4 s and was flown on the
#: defaults, a loiter radius of 0 m)
SILENT_READ_WINDOW_S = 20.0


@dataclass(frozen=True)
class Airframe:
    """One vehicle's flight limits (SI units), and where they came from."""

    key: VehicleKey  # the vehicle (vehicle_key.py)
    min_airspeed_mps: float
    cruise_mps: float
    max_airspeed_mps: float
    bank_limit_deg: float
    wp_loiter_radius_m: float
    capture_radius_m: float
    #: parameter names answered; the fields of names not answered hold the daemon's defaults
    read: tuple[str, ...] = ()
    defaulted: tuple[str, ...] = ()
    #: what the autopilot's adapter capped, and why ("" when nothing)
    capped: str = ""

    def min_turn_radius_m(self, speed_mps: float) -> float:
        """``v**2 / (g tan(bank))``."""
        return speed_mps**2 / (9.80665 * math.tan(math.radians(self.bank_limit_deg)))

    def describe(self) -> str:
        speeds = f"{self.min_airspeed_mps:g}..{self.max_airspeed_mps:g}"
        turn = self.min_turn_radius_m(self.cruise_mps)
        text = (
            f"vehicle {self.key}: airspeed {speeds} m/s (cruise {self.cruise_mps:g}), "
            f"bank limit {self.bank_limit_deg:g} deg (turn radius {turn:.0f} m at cruise), "
            f"loiter radius {self.wp_loiter_radius_m:g} m"
        )
        if self.defaulted:
            text += f" (not reported, assumed: {', '.join(self.defaulted)})"
        if self.capped:
            text += f" ({self.capped})"
        return text


def names_for(vehicle: VehicleState) -> dict[str, tuple[tuple[str, float], ...]]:
    """The parameter names of the vehicle's autopilot (``autopilot_adapter.py``)."""
    return dict(autopilot_for(vehicle).airframe_names)


def default_airframe(system_id: int, cfg: PlannerConfig) -> dict[str, float]:
    """What the daemon assumes of an airframe that does not say: the scenario's speed, v..1.5 v
    (the paper's grid flies a diagonal cell in one step), 45 deg bank, no loiter radius of its
    own (the tightest circle it can fly), 90 m acceptance."""
    v = cfg.speed_mps
    return {
        "min_airspeed_mps": v,
        "cruise_mps": v,
        "max_airspeed_mps": 1.5 * v,
        "bank_limit_deg": 45.0,
        "wp_loiter_radius_m": 0.0,
        "capture_radius_m": 90.0,
    }


def _value(vehicle: VehicleState, options: tuple[tuple[str, float], ...]) -> tuple[str, float]:
    for name, scale in options:
        if name in vehicle.params:
            return name, vehicle.params[name] * scale
    return "", math.nan


def airframe_from_params(vehicle: VehicleState, cfg: PlannerConfig) -> Airframe:
    """The vehicle's airframe from the parameters it has answered (defaults for the rest),
    capped by its autopilot's adapter to what it really flies."""
    fields = default_airframe(vehicle.system_id, cfg)
    read, defaulted = [], []
    for key, options in names_for(vehicle).items():
        name, value = _value(vehicle, options)
        if name and math.isfinite(value) and (value > 0 or key == "wp_loiter_radius_m"):
            fields[key] = abs(value)  # WP_LOITER_RAD < 0 means counter-clockwise
            read.append(name)
        else:
            defaulted.append(options[0][0])
    fields, capped = autopilot_for(vehicle).fly_limits(fields, vehicle.params)
    return Airframe(
        vehicle.key, **fields, read=tuple(read), defaulted=tuple(defaulted), capped=capped
    )


def _all_names(vehicle: VehicleState) -> list[str]:
    """Every parameter name the airframe read asks ``vehicle`` for."""
    names = [name for options in names_for(vehicle).values() for name, _ in options]
    return names + list(autopilot_for(vehicle).limit_names)


def request_params(vehicle: VehicleState, names: list[str]) -> None:
    """PARAM_REQUEST_READ by name (param_index -1) for each name, to the autopilot."""
    for name in names:
        vehicle.link.mav.param_request_read_send(
            vehicle.system_id, AUTOPILOT_COMPONENT_ID, name.encode(), -1
        )


def read_airframes(
    vehicles: list[VehicleState],
    cfg: PlannerConfig,
    wait: Callable[[Callable[[], bool], float], bool],
    window_s: float = READ_WINDOW_S,
) -> list[Airframe]:
    """Ask every vehicle for its limits (all names at once, the missing ones again every
    ``RESEND_S``) and return each one's airframe once every field has an answer, or at the end
    of ``window_s`` with defaults for the rest; a vehicle that has answered none of them is
    asked on for ``SILENT_READ_WINDOW_S`` in all."""

    def missing(v: VehicleState) -> list[str]:
        out = []
        for options in names_for(v).values():
            if not any(name in v.params for name, _ in options):
                out += [name for name, _ in options]
        return out + [name for name in autopilot_for(v).limit_names if name not in v.params]

    started = time.monotonic()
    asked = {v.key: set(_all_names(v)) for v in vehicles}
    while True:
        todo = [(v, missing(v)) for v in vehicles]
        todo = [(v, names) for v, names in todo if names]
        elapsed = time.monotonic() - started
        silent = [v for v, _ in todo if not asked[v.key] & v.params.keys()]
        if not todo or elapsed >= (SILENT_READ_WINDOW_S if silent else window_s):
            break
        if elapsed >= window_s:  # only the silent ones are waited for now
            todo = [(v, names) for v, names in todo if v in silent]
        for v, names in todo:
            request_params(v, names)
        wait(lambda: all(not missing(v) for v in vehicles), RESEND_S)
    return [airframe_from_params(v, cfg) for v in vehicles]


def scenario_plane_model(
    cfg: PlannerConfig,
    airspeed_range_mps: tuple[float, float] | None = None,
    bank_limit_deg: float | None = None,
) -> PlaneModel:
    """The plane model flown until the airframes are read at launch (then
    :func:`fleet_plane_model`): the scenario's speed v, leg timing over ``airspeed_range_mps``
    (default v .. 1.5 v), ``bank_limit_deg`` (default 45 deg). A range that does not hold v is
    refused in one line."""
    v = cfg.speed_mps
    slowest, fastest = airspeed_range_mps or (v, 1.5 * v)
    if not 0 < slowest <= v <= fastest:
        raise UserError(
            f"airspeed range {slowest:g}..{fastest:g} m/s must hold the scenario's speed "
            f"{v:g} m/s (--airspeed-range MIN:MAX with MIN <= speed <= MAX)"
        )
    return PlaneModel(
        speed_mps=v,
        bank_limit_deg=bank_limit_deg or 45.0,
        min_speed_mps=slowest,
        max_speed_mps=fastest,
        slowest_mps=v,
    )


def leg_range_mps(v: float, slowest_allowed: float, fastest_allowed: float) -> tuple[float, float]:
    """The leg timing range for airspeed limits ``slowest_allowed``..``fastest_allowed`` at the
    scenario's speed ``v``: v .. min(1.5 v, fastest) (never below v: a slower plane turns more
    than phi_max in a step; never above the fastest allowed)."""
    low = min(max(v, slowest_allowed), fastest_allowed)
    return low, max(min(1.5 * v, fastest_allowed), low)


def fleet_plane_model(
    airframes: list[Airframe],
    cfg: PlannerConfig,
    airspeed_range_mps: tuple[float, float] | None = None,
    bank_limit_deg: float | None = None,
) -> PlaneModel:
    """One plane model for the fleet: the most restrictive limits of its airframes (smallest
    bank limit, largest loiter and acceptance radii), which the margins and the way home are
    judged with, and, for a fleet of more than one airframe, each plane's own turn
    (``uav_turn_limits``), which the flight envelope predicts each plane's path with
    (``PlaneModel.rows``). Leg timing is each plane's own (``uav_speed_ranges_mps``, airframes
    in UAV order): v .. min(1.5 v, its AIRSPEED_MAX); the fleet's own range
    (``min_speed_mps``..``max_speed_mps``) is the narrowest. ``airspeed_range_mps`` given is
    every plane's range; ``bank_limit_deg`` given overrides the airframes' bank limit."""
    v = cfg.speed_mps
    if airspeed_range_mps is not None:
        ranges = [tuple(airspeed_range_mps)] * len(airframes)
        low, high = airspeed_range_mps
    else:
        ranges = [leg_range_mps(v, a.min_airspeed_mps, a.max_airspeed_mps) for a in airframes]
        low, high = leg_range_mps(
            v,
            max(a.min_airspeed_mps for a in airframes),
            min(a.max_airspeed_mps for a in airframes),
        )
    # each plane's own turn (a mixed fleet's flight prediction: PlaneModel.rows)
    own_turns = tuple(
        (bank_limit_deg or a.bank_limit_deg, a.wp_loiter_radius_m, a.capture_radius_m)
        for a in airframes
    )
    return PlaneModel(
        speed_mps=v,
        bank_limit_deg=bank_limit_deg or min(a.bank_limit_deg for a in airframes),
        capture_radius_m=max(a.capture_radius_m for a in airframes),
        wp_loiter_radius_m=max(a.wp_loiter_radius_m for a in airframes),
        min_speed_mps=low,
        max_speed_mps=high,
        slowest_mps=min(max(a.min_airspeed_mps for a in airframes), v),
        uav_speed_ranges_mps=tuple((float(lo), float(hi)) for lo, hi in ranges),
        uav_turn_limits=own_turns if len(set(own_turns)) > 1 else (),
    )


#: the safety envelope's threat margin never exceeds this (km): about the minimum turn radius of
#: the simulator's 100 m/s plane at 45 deg, the margin the daemon has always flown it with
MAX_THREAT_MARGIN_KM = 1.0


def threat_margin_km(model: PlaneModel, predicted_margin_km: float) -> float:
    """The safety envelope's clearance of each leg from the threat circles for this airframe:
    the circle the plane flies around a guided target at cruise (WP_LOITER_RAD, or its tightest
    turn when wider) plus the flight envelope's predicted margin, at most
    ``MAX_THREAT_MARGIN_KM``. ArduPlane's defaults: 0.08 + 0.25 = 0.33 km; the simulator's plane:
    1 km. A 1 km margin for a plane that circles within 80 m left three ArduPlane SITL planes
    held beside the threat zones of arduplane-3uav for most of a mission (59 overrides in 40
    steps)."""
    loiter_km = float(model.loiter_radius_km(model.speed_mps))
    return min(loiter_km + predicted_margin_km, MAX_THREAT_MARGIN_KM)


#: the separation margin on top of d_min never exceeds this (km): the margin the daemon has
#: always flown the simulator's 100 m/s plane with
MAX_SEPARATION_MARGIN_KM = 1.0


def separation_margin_km(model: PlaneModel, predicted_margin_km: float) -> float:
    """The margin on top of d_min between the UAVs' next cells for this airframe: each of two
    planes may be anywhere on the circle it flies around its guided target (WP_LOITER_RAD, or
    its tightest turn when wider), so two loiter radii, plus the flight envelope's predicted
    separation margin, at most ``MAX_SEPARATION_MARGIN_KM``. ArduPlane's and PX4's defaults
    (80 m circles): 0.46 km; the simulator's plane: 1 km. A 1 km margin for planes that circle
    within 80 m kept three PX4 SIH planes on px4-3uav's 4 x 3.2 km area 1.6 km apart: they
    were pushed into its corners and held there (9 separation overrides in 8 steps)."""
    loiter_km = float(model.loiter_radius_km(model.speed_mps))
    return min(2 * loiter_km + predicted_margin_km, MAX_SEPARATION_MARGIN_KM)


def scenario_warnings(airframes: list[Airframe], cfg: PlannerConfig) -> list[str]:
    """One line per thing the scenario asks that an airframe cannot fly, each with its fix."""
    lines = []
    v, step, cell_m = cfg.speed_mps, cfg.step_s, cfg.cell_km * 1000.0
    for a in airframes:
        if not a.min_airspeed_mps <= v <= a.max_airspeed_mps:
            fit_step = cell_m / a.cruise_mps
            lines.append(
                f"vehicle {a.key} flies {a.min_airspeed_mps:g}..{a.max_airspeed_mps:g} m/s "
                f"but the scenario's UAV speed is {v:g} m/s: set speed_mps = {a.cruise_mps:g} in "
                f"the scenario's [parameters] (its cruise) and step_s = {fit_step:.0f} (one "
                f"{cfg.cell_km:g} km cell per step), or use an airframe that flies {v:g} m/s"
            )
            continue
        diagonal = math.sqrt(2.0) * cell_m / step
        if cell_m / step > a.max_airspeed_mps or diagonal > a.max_airspeed_mps:
            need = math.ceil(math.sqrt(2.0) * cell_m / a.max_airspeed_mps)
            which = "a cell" if cell_m / step > a.max_airspeed_mps else "a diagonal cell"
            lines.append(
                f"vehicle {a.key} cannot fly {which} of {cfg.cell_km:g} km in one "
                f"{step:g} s step (needs {diagonal:.1f} m/s diagonally, AIRSPEED_MAX "
                f"{a.max_airspeed_mps:g}): it will fall behind the grid; set step_s >= {need} "
                f"in the scenario's [parameters], or a smaller cell_km"
            )
    return list(dict.fromkeys(lines))
