"""Waypoint and map files of a mission, made from its result dict (``result.json``).

For each UAV, its planned path (the cells the planner chose) and its flown path (the track that
came back as telemetry, or the offline run's track):

* ``waypoints/uavNN_planned.waypoints`` / ``uavNN_flown.waypoints``: "QGC WPL 110" text, loadable
  by MAVProxy ``wp load``, Mission Planner and pymavlink's ``mavwp``. Item 0 is home; then a
  NAV_TAKEOFF, the path as NAV_WAYPOINTs (straight runs merged), and RETURN_TO_LAUNCH.
* ``plan/uavNN.plan``: a QGroundControl plan of the planned path, with the threat zones as
  geofence exclusion circles.
* ``mission.geojson`` and ``mission.kml``: every track and every threat zone, for map tools.

The formats are described in docs/export.md.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mavlink_wire.protocol import mavlink
from planner.errors import UserError
from planner.geodesy import local_km_to_geodetic
from planner.scenario import Origin

FORMATS = ("wpl", "plan", "geojson", "kml")

MAV_FRAME_GLOBAL = mavlink.MAV_FRAME_GLOBAL
MAV_FRAME_GLOBAL_RELATIVE_ALT = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT
NAV_WAYPOINT = mavlink.MAV_CMD_NAV_WAYPOINT
NAV_TAKEOFF = mavlink.MAV_CMD_NAV_TAKEOFF
NAV_RETURN_TO_LAUNCH = mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH
TAKEOFF_PITCH_DEG = 15.0  # param1 of a plane's NAV_TAKEOFF: minimum climb pitch
QGC_FIRMWARE_ARDUPILOT = 3
QGC_VEHICLE_FIXED_WING = 1
QGC_ALTITUDE_RELATIVE = 1


class ExportError(UserError):
    """A result cannot be exported (missing or malformed fields)."""


@dataclass(frozen=True)
class Waypoint:
    """One mission item as the WPL and .plan formats hold it."""

    command: int
    frame: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    params: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class MissionGeometry:
    """The parts of a result the exporters need, in geodetic form."""

    name: str
    origin: Origin
    altitude_m: float
    speed_mps: float
    threats: list[tuple[float, float, float]]  # (x_km, y_km, radius_km)
    uavs: list[dict[str, Any]]

    def to_geodetic(self, points_km: np.ndarray) -> np.ndarray:
        """(K, 2) km -> (K, 2) (lat, lon) degrees."""
        points_km = np.asarray(points_km, dtype=float).reshape(-1, 2)
        if len(points_km) == 0:
            return np.empty((0, 2))
        lat, lon = local_km_to_geodetic(points_km[:, 0], points_km[:, 1], self.origin)
        return np.stack([lat, lon], axis=1)

    def threat_circles(self) -> list[tuple[float, float, float]]:
        """(lat, lon, radius_m) of each threat zone."""
        if not self.threats:
            return []
        centres = self.to_geodetic(np.array([[t[0], t[1]] for t in self.threats]))
        return [
            (float(c[0]), float(c[1]), t[2] * 1000.0)
            for c, t in zip(centres, self.threats, strict=True)
        ]

    def threat_ring(self, threat: tuple[float, float, float], points: int = 72) -> np.ndarray:
        """Closed ring (points+1, 2) of (lat, lon) around a threat circle."""
        a = np.linspace(0, 2 * np.pi, points, endpoint=False)
        ring = np.stack(
            [threat[0] + threat[2] * np.cos(a), threat[1] + threat[2] * np.sin(a)], axis=1
        )
        geo = self.to_geodetic(ring)
        return np.vstack([geo, geo[:1]])


def _origin_of(value: Any) -> Origin:
    if value is None:
        return Origin()
    if isinstance(value, dict):
        lat = value.get("lat_deg", value.get("lat"))
        lon = value.get("lon_deg", value.get("lon"))
        alt = value.get("alt_m", value.get("alt", Origin.alt_m))
        if lat is None or lon is None:
            raise ExportError("result.json: origin needs lat_deg and lon_deg")
        return Origin(float(lat), float(lon), float(alt))
    if isinstance(value, list | tuple) and len(value) >= 2:
        return Origin(
            float(value[0]), float(value[1]), float(value[2]) if len(value) > 2 else Origin.alt_m
        )
    raise ExportError(f"result.json: origin {value!r} is not {{lat_deg, lon_deg, alt_m}}")


def _threat_of(value: Any) -> tuple[float, float, float]:
    if isinstance(value, dict):
        return (float(value["x_km"]), float(value["y_km"]), float(value["radius_km"]))
    return (float(value[0]), float(value[1]), float(value[2]))


def geometry_of(result: dict[str, Any]) -> MissionGeometry:
    """Read the exporters' inputs from a result dict, naming any missing field."""
    if not isinstance(result, dict) or "uavs" not in result:
        raise ExportError(
            "result has no 'uavs' list; give the result.json of `swarmplan run`, `demo` or `daemon`"
        )
    try:
        threats = [_threat_of(t) for t in result.get("threats", [])]
    except (KeyError, IndexError, TypeError, ValueError):
        raise ExportError("result.json: threats must be {x_km, y_km, radius_km} entries") from None
    config = result.get("config") or {}
    return MissionGeometry(
        name=str(result.get("scenario", "mission")),
        origin=_origin_of(result.get("origin")),
        altitude_m=float(result.get("altitude_m", 500.0)),
        speed_mps=float(result.get("speed_mps", config.get("speed_mps", 100.0))),
        threats=threats,
        uavs=list(result["uavs"]),
    )


def simplify_path(points: np.ndarray, tolerance_km: float = 0.01) -> np.ndarray:
    """Drop points that lie on the straight line between their neighbours (within tolerance)
    and repeated points; the path flown stays the same, the mission gets shorter."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(points) <= 2:
        return points
    kept = [points[0]]
    for k in range(1, len(points) - 1):
        a, p, b = kept[-1], points[k], points[k + 1]
        if np.allclose(p, a):
            continue
        ab = b - a
        length = float(np.hypot(*ab))
        if length > 0:
            off = abs(float(ab[0] * (p - a)[1] - ab[1] * (p - a)[0])) / length
            ahead = float((p - a) @ ab) / length
            if off <= tolerance_km and 0 <= ahead <= length:
                continue
        kept.append(p)
    if not np.allclose(points[-1], kept[-1]):
        kept.append(points[-1])
    return np.array(kept)


def uav_label(uav: dict[str, Any], index: int) -> str:
    return f"uav{int(uav.get('id', index)) + (0 if 'id' in uav else 1):02d}"


def path_km(uav: dict[str, Any], which: str) -> np.ndarray:
    """The planned or flown path (K, 2) in km of one UAV entry of the result."""
    key = {"planned": "planned_km", "flown": "track_km"}[which]
    points = uav.get(key)
    if points is None:
        points = uav.get("track_km") if which == "planned" else None
    if points is None:
        return np.empty((0, 2))
    return np.asarray(points, dtype=float).reshape(-1, 2)


def mission_items(geometry: MissionGeometry, uav: dict[str, Any], which: str) -> list[Waypoint]:
    """Home, takeoff, the path's waypoints, RTL for one UAV."""
    path = path_km(uav, which)
    start = uav.get("start_km")
    start_km = (
        np.asarray(start, float) if start is not None else (path[0] if len(path) else np.zeros(2))
    )
    home = geometry.to_geodetic(start_km.reshape(1, 2))[0]
    items = [
        Waypoint(NAV_WAYPOINT, MAV_FRAME_GLOBAL, home[0], home[1], geometry.origin.alt_m),
        Waypoint(
            NAV_TAKEOFF,
            MAV_FRAME_GLOBAL_RELATIVE_ALT,
            home[0],
            home[1],
            geometry.altitude_m,
            (TAKEOFF_PITCH_DEG, 0.0, 0.0, 0.0),
        ),
    ]
    for lat, lon in geometry.to_geodetic(simplify_path(path)):
        items.append(
            Waypoint(NAV_WAYPOINT, MAV_FRAME_GLOBAL_RELATIVE_ALT, lat, lon, geometry.altitude_m)
        )
    items.append(Waypoint(NAV_RETURN_TO_LAUNCH, MAV_FRAME_GLOBAL_RELATIVE_ALT, 0.0, 0.0, 0.0))
    return items


# ---------------------------------------------------------------------- QGC WPL 110


def wpl_text(items: Sequence[Waypoint]) -> str:
    """ "QGC WPL 110" text: index, current, frame, command, p1-p4, lat, lon, alt, autocontinue."""
    lines = ["QGC WPL 110"]
    for index, item in enumerate(items):
        p = item.params
        lines.append(
            "\t".join(
                [
                    str(index),
                    "1" if index == 0 else "0",
                    str(item.frame),
                    str(item.command),
                    *(f"{v:.8f}" for v in p),
                    f"{item.lat_deg:.8f}",
                    f"{item.lon_deg:.8f}",
                    f"{item.alt_m:.6f}",
                    "1",
                ]
            )
        )
    return "\n".join(lines) + "\n"


def write_wpl(geometry: MissionGeometry, out_dir: Path) -> list[Path]:
    folder = out_dir / "waypoints"
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for index, uav in enumerate(geometry.uavs):
        for which in ("planned", "flown"):
            if which == "flown" and uav.get("track_km") is None:
                continue
            path = folder / f"{uav_label(uav, index)}_{which}.waypoints"
            path.write_text(wpl_text(mission_items(geometry, uav, which)))
            written.append(path)
    return written


# ---------------------------------------------------------------------- QGroundControl .plan


def _plan_item(item: Waypoint, jump_id: int) -> dict[str, Any]:
    p = item.params
    return {
        "AMSLAltAboveTerrain": None,
        "Altitude": item.alt_m,
        "AltitudeMode": QGC_ALTITUDE_RELATIVE,
        "autoContinue": True,
        "command": item.command,
        "doJumpId": jump_id,
        "frame": item.frame,
        "params": [p[0], p[1], p[2], p[3], item.lat_deg, item.lon_deg, item.alt_m],
        "type": "SimpleItem",
    }


def plan_document(geometry: MissionGeometry, uav: dict[str, Any]) -> dict[str, Any]:
    """A QGroundControl .plan (fileType Plan, version 1) of one UAV's planned path."""
    items = mission_items(geometry, uav, "planned")
    home = items[0]
    return {
        "fileType": "Plan",
        "geoFence": {
            "circles": [
                {
                    "circle": {"center": [lat, lon], "radius": radius},
                    "inclusion": False,
                    "version": 1,
                }
                for lat, lon, radius in geometry.threat_circles()
            ],
            "polygons": [],
            "version": 2,
        },
        "groundStation": "QGroundControl",
        "mission": {
            "cruiseSpeed": geometry.speed_mps,
            "firmwareType": QGC_FIRMWARE_ARDUPILOT,
            "globalPlanAltitudeMode": QGC_ALTITUDE_RELATIVE,
            "hoverSpeed": 5,
            "items": [_plan_item(item, k + 1) for k, item in enumerate(items[1:])],
            "plannedHomePosition": [home.lat_deg, home.lon_deg, home.alt_m],
            "vehicleType": QGC_VEHICLE_FIXED_WING,
            "version": 2,
        },
        "rallyPoints": {"points": [], "version": 2},
        "version": 1,
    }


def write_plan(geometry: MissionGeometry, out_dir: Path) -> list[Path]:
    folder = out_dir / "plan"
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for index, uav in enumerate(geometry.uavs):
        path = folder / f"{uav_label(uav, index)}.plan"
        path.write_text(json.dumps(plan_document(geometry, uav), indent=4))
        written.append(path)
    return written


# ---------------------------------------------------------------------- GeoJSON and KML


def _tracks(geometry: MissionGeometry) -> Iterable[tuple[str, str, dict[str, Any], np.ndarray]]:
    """(label, which, uav, (K, 2) lat/lon) of every non-empty path."""
    for index, uav in enumerate(geometry.uavs):
        for which in ("planned", "flown"):
            if which == "planned" and uav.get("planned_km") is None:
                continue
            points = path_km(uav, which)
            if len(points) >= 1:
                yield uav_label(uav, index), which, uav, geometry.to_geodetic(points)


def geojson_document(geometry: MissionGeometry) -> dict[str, Any]:
    """FeatureCollection: a LineString per track, a Polygon per threat zone (lon, lat order)."""
    features: list[dict[str, Any]] = []
    for label, which, uav, geo in _tracks(geometry):
        coords = [[float(lon), float(lat)] for lat, lon in geo]
        if len(coords) == 1:
            coords.append(coords[0])
        features.append(
            {
                "type": "Feature",
                "geometry": {"type": "LineString", "coordinates": coords},
                "properties": {
                    "kind": f"{which}_track",
                    "uav": label,
                    "returned": uav.get("returned"),
                    "distance_km": uav.get("distance_km"),
                },
            }
        )
    for k, threat in enumerate(geometry.threats):
        ring = [[float(lon), float(lat)] for lat, lon in geometry.threat_ring(threat)]
        features.append(
            {
                "type": "Feature",
                "geometry": {"type": "Polygon", "coordinates": [ring]},
                "properties": {"kind": "threat", "index": k, "radius_km": threat[2]},
            }
        )
    return {"type": "FeatureCollection", "name": geometry.name, "features": features}


def kml_document(geometry: MissionGeometry) -> ET.ElementTree:
    """KML 2.2: a LineString placemark per track, a Polygon per threat zone."""
    ns = "http://www.opengis.net/kml/2.2"
    kml = ET.Element("kml", xmlns=ns)
    doc = ET.SubElement(kml, "Document")
    ET.SubElement(doc, "name").text = geometry.name
    for style, colour in (("planned", "ff00a5ff"), ("flown", "ffff0000"), ("threat", "7f0000ff")):
        st = ET.SubElement(doc, "Style", id=style)
        line = ET.SubElement(st, "LineStyle")
        ET.SubElement(line, "color").text = colour
        ET.SubElement(line, "width").text = "2"
        poly = ET.SubElement(st, "PolyStyle")
        ET.SubElement(poly, "color").text = colour
    alt = geometry.altitude_m
    for label, which, _uav, geo in _tracks(geometry):
        mark = ET.SubElement(doc, "Placemark")
        ET.SubElement(mark, "name").text = f"{label} {which}"
        ET.SubElement(mark, "styleUrl").text = f"#{which}"
        line = ET.SubElement(mark, "LineString")
        ET.SubElement(line, "altitudeMode").text = "relativeToGround"
        ET.SubElement(line, "coordinates").text = " ".join(
            f"{lon:.7f},{lat:.7f},{alt:g}" for lat, lon in geo
        )
    for k, threat in enumerate(geometry.threats):
        mark = ET.SubElement(doc, "Placemark")
        ET.SubElement(mark, "name").text = f"threat {k + 1} ({threat[2]:g} km)"
        ET.SubElement(mark, "styleUrl").text = "#threat"
        ring = ET.SubElement(
            ET.SubElement(ET.SubElement(mark, "Polygon"), "outerBoundaryIs"), "LinearRing"
        )
        ET.SubElement(ring, "coordinates").text = " ".join(
            f"{lon:.7f},{lat:.7f},0" for lat, lon in geometry.threat_ring(threat)
        )
    ET.indent(kml)
    return ET.ElementTree(kml)


def write_geojson(geometry: MissionGeometry, out_dir: Path) -> list[Path]:
    path = out_dir / "mission.geojson"
    path.write_text(json.dumps(geojson_document(geometry)))
    return [path]


def write_kml(geometry: MissionGeometry, out_dir: Path) -> list[Path]:
    path = out_dir / "mission.kml"
    kml_document(geometry).write(path, encoding="utf-8", xml_declaration=True)
    return [path]


WRITERS = {"wpl": write_wpl, "plan": write_plan, "geojson": write_geojson, "kml": write_kml}


def export(
    result: dict[str, Any], out_dir: str | Path, formats: Iterable[str] = FORMATS
) -> list[Path]:
    """Write the chosen formats of a result into ``out_dir``; returns the files written."""
    geometry = geometry_of(result)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    for name in formats:
        if name not in WRITERS:
            raise ExportError(f"unknown format {name!r}; use one of {', '.join(FORMATS)}")
        written += WRITERS[name](geometry, out)
    return written


def export_all(result: dict[str, Any], out_dir: str | Path) -> list[Path]:
    """Every format into ``out_dir`` (what ``swarmplan run`` and ``demo`` call)."""
    return export(result, out_dir, FORMATS)


__all__ = [
    "export",
    "export_all",
    "FORMATS",
    "wpl_text",
    "plan_document",
    "geojson_document",
    "kml_document",
    "geometry_of",
    "simplify_path",
    "ExportError",
]
