"""The sensor looks of one decision period: every airborne vehicle looks once, at its position as
reported (degE7, so that a receiver converting the reported lat/lon with planner.geodesy finds
the very same cell), and its camera sends what it saw as look messages
(``mavlink_wire/looks.py``, docs/mavlink.md "Sensor looks").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from mavlink_wire.looks import look_messages
from planner.geodesy import geodetic_to_local_km, local_km_to_geodetic
from planner.grid import Grid
from planner.scenario import Origin
from planner.sensor_model import SensorReport
from sim_gateway.fixed_wing import FleetKinematics
from sim_gateway.world import World


@dataclass(frozen=True)
class Looks:
    """The looks of the vehicles in rows ``flying`` of the fleet (the k-th look is of row
    ``flying[k]``), taken at one instant."""

    flying: np.ndarray
    lat_e7: np.ndarray
    lon_e7: np.ndarray
    xy_km: np.ndarray  # where each look was taken: the reported position, in local km
    reports: list[SensorReport]
    cells: np.ndarray  # the grid cell each look was taken from

    @classmethod
    def take(cls, world: World, grid: Grid, origin: Origin, fleet: FleetKinematics) -> Looks:
        """One look of every airborne vehicle of ``fleet`` in ``world``."""
        flying = np.flatnonzero(fleet.airborne)
        lat, lon = local_km_to_geodetic(
            fleet.x_m[flying] / 1000.0, fleet.y_m[flying] / 1000.0, origin
        )
        lat_e7, lon_e7 = np.rint(lat * 1e7).astype(np.int64), np.rint(lon * 1e7).astype(np.int64)
        x_km, y_km = geodetic_to_local_km(lat_e7 / 1e7, lon_e7 / 1e7, origin)
        xy = np.stack([x_km, y_km], axis=1)
        return cls(flying, lat_e7, lon_e7, xy, world.sense(xy), grid.cell_of(xy))

    def messages(
        self,
        k: int,
        look_index: int,
        boot_ms: int,
        utc_us: int,
        home_amsl_m: float,
        relative_alt_m: float,
    ) -> list[mavlink.MAVLink_camera_image_captured_message]:
        """The look messages of the ``k``-th look, the vehicle's look number ``look_index``."""
        report = self.reports[k]
        detected = report.cells[report.detected] - self.cells[k]
        rel_mm = round(relative_alt_m * 1000)
        return look_messages(
            ((int(dx), int(dy)) for dx, dy in detected),
            look_index,
            boot_ms,
            utc_us,
            int(self.lat_e7[k]),
            int(self.lon_e7[k]),
            round(home_amsl_m * 1000) + rel_mm,
            rel_mm,
        )
