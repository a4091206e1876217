"""Local mission frame <-> geodetic coordinates, with pymap3d's geodesic (Vincenty) routines.

The mission frame has its origin at the area's south-west corner (the scenario's ``origin``),
x east and y north in km. A local point is the geodesic reached from the origin along the
azimuth ``atan2(x, y)`` for the distance ``hypot(x, y)`` (an azimuthal equidistant projection),
so distances from the origin are exact on the WGS-84 ellipsoid and the conversion round-trips.
Altitudes are handled separately by the callers (metres above the origin's altitude).
"""

from __future__ import annotations

import numpy as np
from pymap3d import vincenty

from planner.scenario import Origin


def local_km_to_geodetic(
    x_km: np.ndarray | float, y_km: np.ndarray | float, origin: Origin
) -> tuple[np.ndarray, np.ndarray]:
    """(lat_deg, lon_deg) of points given in the local frame (arrays of any shape)."""
    x = np.atleast_1d(np.asarray(x_km, dtype=float))
    y = np.atleast_1d(np.asarray(y_km, dtype=float))
    x, y = np.broadcast_arrays(x, y)
    distance_m = np.hypot(x, y) * 1000.0
    azimuth_deg = np.degrees(np.arctan2(x, y)) % 360.0
    lat = np.full(x.shape, origin.lat_deg)
    lon = np.full(x.shape, origin.lon_deg)
    moved = distance_m > 0
    if moved.any():
        lat_m, lon_m = vincenty.vreckon(
            origin.lat_deg, origin.lon_deg, distance_m[moved], azimuth_deg[moved]
        )
        lat[moved], lon[moved] = lat_m, lon_m
    return lat, lon


def geodetic_to_local_km(
    lat_deg: np.ndarray | float, lon_deg: np.ndarray | float, origin: Origin
) -> tuple[np.ndarray, np.ndarray]:
    """(x_km, y_km) in the local frame of geodetic points (arrays of any shape)."""
    lat = np.atleast_1d(np.asarray(lat_deg, dtype=float))
    lon = np.atleast_1d(np.asarray(lon_deg, dtype=float))
    lat, lon = np.broadcast_arrays(lat, lon)
    x = np.zeros(lat.shape)
    y = np.zeros(lat.shape)
    moved = (lat != origin.lat_deg) | (lon != origin.lon_deg)
    if moved.any():
        distance_m, azimuth_deg = vincenty.vdist(
            origin.lat_deg, origin.lon_deg, lat[moved], lon[moved]
        )
        az = np.radians(np.asarray(azimuth_deg, dtype=float))
        x[moved] = np.asarray(distance_m) * np.sin(az) / 1000.0
        y[moved] = np.asarray(distance_m) * np.cos(az) / 1000.0
    return x, y
