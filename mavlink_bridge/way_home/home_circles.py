"""How fast each plane circles its home at the end of a mission, so that close homes keep d_min.

RTL circles home at the loiter radius of its airspeed; two planes whose homes are close would
come within d_min there at cruise speed. :func:`home_circle_speeds` slows such planes down
(not below the autopilot's AIRSPEED_MIN) and names the homes too close even then.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mavlink_bridge.vehicles.autopilot_adapter import RTL_COMMANDS
from mavlink_bridge.vehicles.flight_prediction import PlaneModel
from mavlink_bridge.vehicles.guided_commands import Command, change_speed_command
from mavlink_bridge.vehicles.vehicle_key import VehicleKey


@dataclass(frozen=True)
class HomeCircles:
    """How fast each plane circles its home so that the circles keep d_min
    (:func:`home_circle_speeds`): ``speeds_mps`` for the planes that must fly slower than
    cruise, and the pairs of homes (system ids, km apart) too close even at the slowest."""

    speeds_mps: dict[VehicleKey, float] = field(default_factory=dict)
    too_close: list[tuple[VehicleKey, VehicleKey, float]] = field(default_factory=list)


def home_circle_speeds(
    homes_km: dict[VehicleKey, np.ndarray], plane: PlaneModel, d_min_km: float
) -> HomeCircles:
    """The airspeed at which each plane circles its home at the end of a mission, so that two
    planes whose homes are close keep d_min there.

    RTL circles home at the loiter radius, r(v) = the tightest turn at airspeed v (or
    WP_LOITER_RAD when wider), and a plane arriving at its home strays up to a loiter
    diameter before it is on its circle (``PlaneModel.loiter_reach_km``). Two homes D apart
    keep d_min while one arrives and the other circles when D >= d_min + 2 r(v) + r(v), so a
    plane flies home at the fastest v <= cruise that meets this for its nearest home, and not
    slower than the autopilot's AIRSPEED_MIN (``PlaneModel.slowest_mps``). Where even that is
    too fast for two planes circling (D < d_min + 2 r), the pair is in ``too_close``: the
    scenario put their homes too near for the airframe (paper-10uav seed 3 at 100 m/s: homes
    2.37 km apart, circles of 1.07 km, 0.70 km between the planes)."""
    ids = sorted(homes_km)
    circles = HomeCircles()
    if len(ids) < 2:
        return circles
    xy = np.array([homes_km[i] for i in ids], dtype=float)
    gap = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(gap, np.inf)
    cruise, slowest = plane.speed_mps, min(plane.slowest_mps, plane.speed_mps)
    # fastest speed whose loiter radius is at most (D - d_min) / 3
    room_km = np.maximum(gap.min(axis=1) - d_min_km, 0.0) / 3.0
    speeds = np.clip(plane.fastest_for_loiter_radius_mps(room_km), slowest, cruise)
    for sid, speed in zip(ids, speeds, strict=True):
        if speed < cruise:
            circles.speeds_mps[sid] = float(speed)
    radius_km = np.array([float(plane.loiter_radius_km(s)) for s in speeds])
    short = gap < d_min_km + radius_km[:, None] + radius_km[None, :]
    for a, b in zip(*np.nonzero(np.triu(short)), strict=True):
        circles.too_close.append((ids[a], ids[b], float(gap[a, b])))
    return circles


def circle_lines(circles: HomeCircles, d_min_km: float) -> list[str]:
    """What the daemon says of ``circles``: who circles home slower, which homes are too close."""
    by_speed: dict[float, list[VehicleKey]] = {}
    for sid, speed in sorted(circles.speeds_mps.items()):
        by_speed.setdefault(round(speed), []).append(sid)
    lines = [
        f"vehicle{'s' if len(ids) > 1 else ''} {', '.join(map(str, ids))} circle home at "
        f"{speed} m/s: their homes are close to another's, and a circle at cruise would "
        "come within d_min"
        for speed, ids in by_speed.items()
    ]
    lines += [
        f"warning: the homes of vehicles {a} and {b} are {km:.2f} km apart: circling them "
        f"keeps d_min only for homes {d_min_km:g} km and two loiter circles apart at "
        "AIRSPEED_MIN; start them farther apart"
        for a, b, km in circles.too_close
    ]
    return lines


def slow_circle_commands(circles: HomeCircles, sent: list[Command]) -> list[Command]:
    """After RTL was accepted: the home circle's airspeed (DO_CHANGE_SPEED) to the planes of
    ``sent`` that fly home slower than cruise. Sent after the mode change, which resets a speed
    commanded before it (ArduPlane)."""
    speeds = circles.speeds_mps
    return [
        change_speed_command(c.vehicle, speeds[c.vehicle.key])
        for c in sent
        if c.command in RTL_COMMANDS and c.accepted and c.vehicle.key in speeds
    ]
