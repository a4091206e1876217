"""Where a plane sent to a point will fly: the daemon's model of ArduPlane guided flight.

A plane given a DO_REPOSITION target flies towards it at constant airspeed, turning no faster
than a coordinated turn at its bank limit, and on arrival (within WP_RADIUS, or when the point
passes close abeam, inside its turn circle) loiters clockwise around it on the tightest circle it
can fly (the requested radius, never below ~1.05 x the minimum turn radius). The daemon predicts
that path for every candidate guided target, so the safety envelope can judge the path the plane
will really fly (turn radius, loiter circle, lag on diagonal legs) rather than the cell centres
the planner thinks in::

    turn_rate = g * tan(bank_limit) / V            (5.6 deg/s at 100 m/s, 45 deg)
    min_turn_radius = V**2 / (g * tan(bank_limit))  (1.02 km)

Vectorised over rows (UAVs x candidates). Positions in km in the mission frame (x east, y
north); courses in radians counter-clockwise from east, as the planner's grid headings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GRAVITY_MPS2 = 9.80665


@dataclass(frozen=True)
class PlaneModel:
    """What the daemon assumes of every plane (ArduPlane parameter names in the comments)."""

    speed_mps: float = 100.0  # AIRSPEED_CRUISE: the scenario's UAV speed
    bank_limit_deg: float = 45.0  # ROLL_LIMIT_DEG (ArduPlane's default)
    capture_radius_m: float = 90.0  # WP_RADIUS
    loiter_radius_factor: float = 1.05  # tightest loiter flown, in minimum turn radii
    loiter_gain: float = 2.0  # how hard the loiter path converges onto its circle

    @property
    def min_turn_radius_km(self) -> float:
        return self.speed_mps**2 / (GRAVITY_MPS2 * np.tan(np.radians(self.bank_limit_deg))) / 1e3

    @property
    def turn_rate_radps(self) -> float:
        return GRAVITY_MPS2 * float(np.tan(np.radians(self.bank_limit_deg))) / self.speed_mps

    @property
    def loiter_radius_km(self) -> float:
        return self.loiter_radius_factor * self.min_turn_radius_km


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2 * np.pi) - np.pi


def predict_paths(
    model: PlaneModel,
    xy_km: np.ndarray,
    course_rad: np.ndarray,
    aim_km: np.ndarray,
    horizon_s: float,
    sample_s: float = 1.0,
    dt_s: float = 0.2,
) -> np.ndarray:
    """Positions (M, S + 1, 2) every ``sample_s`` from now (index 0) to ``horizon_s`` of planes
    at ``xy_km`` (M, 2) flying ``course_rad`` (M,) after being sent to ``aim_km`` (M, 2)."""
    p = np.array(xy_km, dtype=float, copy=True).reshape(-1, 2)
    course = np.array(course_rad, dtype=float, copy=True).reshape(-1)
    aim = np.asarray(aim_km, dtype=float).reshape(-1, 2)
    m = len(p)
    step_km = model.speed_mps * dt_s / 1000.0
    max_turn = model.turn_rate_radps * dt_s
    capture_km = model.capture_radius_m / 1000.0
    passed_km = 2.0 * model.min_turn_radius_km
    loiter_km = model.loiter_radius_km
    orbiting = np.zeros(m, dtype=bool)
    per_sample = max(1, round(sample_s / dt_s))
    samples = max(1, round(horizon_s / sample_s))
    out = np.empty((m, samples + 1, 2))
    out[:, 0] = p
    for k in range(samples * per_sample):
        d = aim - p
        dist = np.hypot(d[:, 0], d[:, 1])
        to_aim = np.arctan2(d[:, 1], d[:, 0])
        desired = to_aim.copy()
        if orbiting.any():
            # clockwise loiter: tangent = bearing from the centre - 90 deg, steered onto the circle
            from_centre = to_aim[orbiting] + np.pi
            correction = np.arctan(model.loiter_gain * (dist[orbiting] - loiter_km) / loiter_km)
            desired[orbiting] = from_centre - (np.pi / 2 + correction)
        turn = np.clip(_wrap(desired - course), -max_turn, max_turn)
        mid = course + 0.5 * turn
        course = course + turn
        p = p + step_km * np.stack([np.cos(mid), np.sin(mid)], axis=1)
        if not orbiting.all():
            d = aim - p
            dist = np.hypot(d[:, 0], d[:, 1])
            ahead = np.cos(course) * d[:, 0] + np.sin(course) * d[:, 1]
            orbiting |= (dist <= capture_km) | ((ahead < 0) & (dist < passed_km))
        if (k + 1) % per_sample == 0:
            out[:, (k + 1) // per_sample] = p
    return out
