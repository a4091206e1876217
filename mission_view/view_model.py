"""What the page shows, as plain data: the mission's fixed layout (area, threats, lat/lon lines)
and one ``StepView`` per decision step (vehicles, guided targets, true targets where known, and
the events of the step). Everything is in the mission frame (km, x east, y north from the area's
south-west corner, ``planner.geodesy``); lat/lon appear only as the labelled lines of constant
latitude and longitude, converted exactly.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from planner.geodesy import geodetic_to_local_km, local_km_to_geodetic
from planner.scenario import Scenario

#: Event kinds of the timeline.
EVENT_KINDS = ("engagement", "miss", "threat", "override", "refusal", "warning", "link", "phase")

#: Spacings (degrees) tried for the lines of constant latitude / longitude: the largest giving
#: at least three lines across the area is used.
GRATICULE_STEPS_DEG = (1.0, 0.5, 0.2, 0.1, 0.05, 0.02, 0.01, 0.005)


@dataclass
class VehicleView:
    """One vehicle at one decision step."""

    x_km: float
    y_km: float
    heading_deg: float  # course, counter-clockwise from east (the mission frame's convention)
    active: bool = True  # heard (not lost) and flying
    target_km: tuple[float, float] | None = None  # the guided target (or next cell) sent
    mode: str = ""  # flight mode (MAVLink) or "grid" (offline)
    planner_mode: str = ""  # why the planner chose the move (planner.planner_interface.MODES)
    ground_speed_mps: float | None = None
    airspeed_mps: float | None = None  # the airspeed commanded for the leg
    last_heard_s: float | None = None  # seconds since the vehicle was last heard
    signed: bool | None = None  # MAVLink 2 signing on its link (None: no link)
    done: bool = False
    # what the autopilot reports, where it does (None: not reported, or offline)
    alt_m: float | None = None  # above home (GLOBAL_POSITION_INT relative_alt)
    battery_pct: int | None = None  # SYS_STATUS battery_remaining
    gps_fix: int | None = None  # GPS_RAW_INT fix_type (GPS_FIX_TYPE_*)
    home_km: tuple[float, float] | None = None  # its home (HOME_POSITION; offline: its start)
    last_look: int | None = None  # index of its newest sensor look
    last_look_s: float | None = None  # seconds since that look arrived
    #: out of the mission for good and flying home, and why ("sent home (operator)"); None: not
    sent_home: str | None = None


@dataclass
class TimelineEvent:
    step: int
    kind: str  # one of EVENT_KINDS
    text: str
    uav: int | None = None  # 0-based
    x_km: float | None = None  # where (an engagement)
    y_km: float | None = None


@dataclass
class StepView:
    """Decision step ``step``: vehicles, coverage and engagement totals, events."""

    step: int
    vehicles: list[VehicleView]
    coverage: float = 0.0
    engaged: int = 0
    engaged_value: float = 0.0
    late: bool = False
    late_steps: int = 0
    wall_s: float = 0.0  # wall clock since the first decision step
    #: true targets (the simulator's or the offline world's), [id, x_km, y_km, alive]; None where
    #: the truth is not known (a real autopilot)
    truth: list[list[float]] | None = None
    events: list[TimelineEvent] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        doc = asdict(self)
        doc["wall_s"] = round(doc["wall_s"], 4)
        for v in doc["vehicles"]:
            v["x_km"], v["y_km"] = round(v["x_km"], 4), round(v["y_km"], 4)
            v["heading_deg"] = round(v["heading_deg"], 1)
            for key in ("ground_speed_mps", "airspeed_mps", "last_heard_s", "alt_m", "last_look_s"):
                if v[key] is not None:
                    v[key] = round(v[key], 2)
            for key in ("target_km", "home_km"):
                if v[key] is not None:
                    v[key] = [round(c, 4) for c in v[key]]
        return doc


def graticule(scenario: Scenario) -> list[dict[str, Any]]:
    """Lines of constant latitude and longitude across the area, each as points in km with its
    label (``{"label": "35.40°S", "axis": "lat", "points": [[x, y], ...]}``)."""
    w, h = scenario.config.area_km
    corners_x = np.array([0.0, w, 0.0, w])
    corners_y = np.array([0.0, 0.0, h, h])
    lat, lon = local_km_to_geodetic(corners_x, corners_y, scenario.origin)
    lines = []
    for axis, values in (("lat", lat), ("lon", lon)):
        lo, hi = float(values.min()), float(values.max())
        step = next(
            (s for s in GRATICULE_STEPS_DEG if math.floor(hi / s) - math.ceil(lo / s) + 1 >= 3),
            GRATICULE_STEPS_DEG[-1],
        )
        first, last = math.ceil(lo / step), math.floor(hi / step)
        for k in range(first, last + 1):
            value = round(k * step, 6)
            samples = np.linspace(0.0, 1.0, 21)
            if axis == "lat":
                la = np.full(samples.shape, value)
                lo_ = lon.min() + samples * (lon.max() - lon.min())
            else:
                lo_ = np.full(samples.shape, value)
                la = lat.min() + samples * (lat.max() - lat.min())
            x, y = geodetic_to_local_km(la, lo_, scenario.origin)
            hemisphere = (
                ("N" if value >= 0 else "S") if axis == "lat" else ("E" if value >= 0 else "W")
            )
            decimals = max(0, -math.floor(math.log10(step)))
            label = f"{abs(value):.{decimals}f}°{hemisphere}"
            points = [[round(float(a), 3), round(float(b), 3)] for a, b in zip(x, y, strict=True)]
            lines.append({"axis": axis, "label": label, "points": points})
    return lines


def geo_grid(scenario: Scenario, samples: int = 17, margin: float = 0.5) -> dict[str, Any]:
    """Latitude and longitude of a ``samples`` x ``samples`` grid of mission-frame points over
    the area and ``margin`` of it around: the page interpolates them (bilinearly: within ~2 m over
    the paper's 100 km area) for its cursor readout and to place map tiles."""
    w, h = scenario.config.area_km
    xs = np.linspace(-margin * w, (1 + margin) * w, samples)
    ys = np.linspace(-margin * h, (1 + margin) * h, samples)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")  # [ix][iy]
    lat, lon = local_km_to_geodetic(gx, gy, scenario.origin)
    return {
        "x_km": [round(float(x), 4) for x in xs],
        "y_km": [round(float(y), 4) for y in ys],
        "lat": np.round(lat, 8).tolist(),
        "lon": np.round(lon, 8).tolist(),
    }


def mission_layout(
    scenario: Scenario,
    *,
    seed: int,
    steps: int,
    uav_count: int,
    source: str,
    live: bool,
    truth: bool,
    layer_shape: tuple[int, int],
    layer_scales: dict[str, str],
) -> dict[str, Any]:
    """The fixed part of the page: sent once to every client and written first in a replay."""
    cfg = scenario.config
    return {
        "type": "mission",
        "scenario": scenario.name,
        "seed": seed,
        "steps": steps,
        "uav_count": uav_count,
        "source": source,  # "mavlink" or "offline"
        "live": live,
        "truth": truth,
        "area_km": list(cfg.area_km),
        "cell_km": cfg.cell_km,
        "step_s": cfg.step_s,
        "origin": {"lat": scenario.origin.lat_deg, "lon": scenario.origin.lon_deg},
        "threats": [
            {"x_km": t.x_km, "y_km": t.y_km, "radius_km": t.radius_km} for t in scenario.threats
        ],
        "targets": {str(t.id): {"value": t.value, "kind": t.kind} for t in scenario.targets},
        "graticule": graticule(scenario),
        "geo_grid": geo_grid(scenario),
        "layer_shape": list(layer_shape),
        "layer_scales": layer_scales,
    }
