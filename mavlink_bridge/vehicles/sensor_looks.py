"""Sensor looks received over MAVLink, turned into the planner's SensorReport.

A look arrives as CAMERA_IMAGE_CAPTURED from the vehicle's camera (component 100): lat/lon of
the place it was taken, ``image_index`` = look number, ``file_url`` = ``"look:"`` followed by the
detected cells as offsets from the look cell (``"look:0,1;-2,0"``; continuation frames with the
same index start ``"look+:"``). The footprint is every in-area cell whose centre lies within the
detection radius of the look cell's centre; the cells not listed were seen and reported nothing.
"""

from __future__ import annotations

import numpy as np

from mavlink_bridge.vehicles.vehicle_state import Look
from planner.geodesy import geodetic_to_local_km
from planner.grid import Grid
from planner.scenario import Origin
from planner.sensor_model import SensorReport


def look_cell(look: Look, grid: Grid, origin: Origin) -> np.ndarray:
    """The grid cell (2,) the look was taken from."""
    x, y = geodetic_to_local_km(look.lat_deg, look.lon_deg, origin)
    return grid.cell_of(np.array([x[0], y[0]]))


def look_report(
    look: Look,
    grid: Grid,
    origin: Origin,
    detection_radius_km: float,
    cell: np.ndarray | None = None,
) -> SensorReport:
    """The SensorReport of one look: its whole footprint, detected where the look said so.
    ``cell``: the look's cell (``look_cell``) when the caller has already converted it."""
    centre = look_cell(look, grid, origin) if cell is None else np.asarray(cell)
    offsets = grid.disc_offsets(detection_radius_km)
    cells = centre[None, :] + offsets
    keep = grid.inside(cells)
    cells, offsets = cells[keep], offsets[keep]
    detected = np.zeros(len(cells), dtype=bool)
    if look.offsets:
        hits = {(int(dx), int(dy)) for dx, dy in look.offsets}
        detected = np.array([(int(dx), int(dy)) in hits for dx, dy in offsets], dtype=bool)
    return SensorReport(cells=cells.astype(np.int64), detected=detected)
