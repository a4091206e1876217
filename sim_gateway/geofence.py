"""Geofence exclusion circles (MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION) and their enforcement.

A vehicle's uploaded fence is turned into circles in the local frame (metres). Enforcement, as
documented in docs/simulator.md: a guided target inside a circle is refused (COMMAND_ACK DENIED),
and a vehicle found inside a circle is in breach: the geofence health bit of SYS_STATUS drops and
the FENCE_ACTION (RTL by default) is taken once per breach.
"""

from __future__ import annotations

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from planner.geodesy import geodetic_to_local_km
from planner.scenario import Origin
from sim_gateway.mission_store import MissionItem


def exclusion_circles(items: list[MissionItem], origin: Origin) -> np.ndarray:
    """(M, 3) array of (x_m, y_m, radius_m) of the exclusion circles among fence items."""
    circles = [it for it in items if it.command == mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION]
    if not circles:
        return np.zeros((0, 3))
    lat = np.array([c.lat_deg for c in circles])
    lon = np.array([c.lon_deg for c in circles])
    x_km, y_km = geodetic_to_local_km(lat, lon, origin)
    radius = np.array([c.param1 for c in circles], dtype=float)
    return np.stack([x_km * 1000.0, y_km * 1000.0, radius], axis=1)


def point_excluded(circles: np.ndarray, x_m: float, y_m: float) -> bool:
    """Whether a point lies inside any of the circles."""
    if len(circles) == 0:
        return False
    d = np.hypot(circles[:, 0] - x_m, circles[:, 1] - y_m)
    return bool(np.any(d <= circles[:, 2]))


class FleetFence:
    """Every vehicle's exclusion circles in one set of arrays, for one breach check per tick."""

    def __init__(self, n_vehicles: int) -> None:
        self.n = n_vehicles
        self.per_vehicle: list[np.ndarray] = [np.zeros((0, 3)) for _ in range(n_vehicles)]
        self._rebuild()

    def set_circles(self, index: int, circles: np.ndarray) -> None:
        self.per_vehicle[index] = circles
        self._rebuild()

    def _rebuild(self) -> None:
        owners = [np.full(len(c), i) for i, c in enumerate(self.per_vehicle)]
        self.owner = np.concatenate(owners).astype(np.int64) if owners else np.zeros(0, np.int64)
        stacked = [c for c in self.per_vehicle if len(c)]
        self.circles = np.concatenate(stacked) if stacked else np.zeros((0, 3))

    def inside(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """(N,) bool: each vehicle is inside one of its own exclusion circles."""
        breached = np.zeros(self.n, dtype=bool)
        if len(self.circles) == 0:
            return breached
        d = np.hypot(x_m[self.owner] - self.circles[:, 0], y_m[self.owner] - self.circles[:, 1])
        breached[self.owner[d <= self.circles[:, 2]]] = True
        return breached
