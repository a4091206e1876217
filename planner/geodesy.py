"""Local mission frame <-> geodetic coordinates, through pymap3d's ENU conversions.

The mission frame has its origin at the area's south-west corner (the scenario's ``origin``),
x east and y north in km; altitudes are metres above the origin's altitude unless named AMSL.
"""

from __future__ import annotations

import numpy as np
import pymap3d

from planner.scenario import Origin


def local_km_to_geodetic(
    x_km: np.ndarray | float, y_km: np.ndarray | float, origin: Origin, up_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lat_deg, lon_deg, alt_m AMSL) of points given in the local frame."""
    lat, lon, alt = pymap3d.enu2geodetic(
        np.asarray(x_km, dtype=float) * 1000.0,
        np.asarray(y_km, dtype=float) * 1000.0,
        up_m,
        origin.lat_deg,
        origin.lon_deg,
        origin.alt_m,
    )
    return np.asarray(lat), np.asarray(lon), np.asarray(alt)


def geodetic_to_local_km(
    lat_deg: np.ndarray | float, lon_deg: np.ndarray | float, origin: Origin, alt_m: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(x_km, y_km) in the local frame of geodetic points (altitude defaults to the origin's)."""
    east, north, _ = pymap3d.geodetic2enu(
        lat_deg,
        lon_deg,
        origin.alt_m if alt_m is None else alt_m,
        origin.lat_deg,
        origin.lon_deg,
        origin.alt_m,
    )
    return np.asarray(east) / 1000.0, np.asarray(north) / 1000.0
