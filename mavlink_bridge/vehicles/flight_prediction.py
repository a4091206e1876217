"""Where a plane sent to a point will fly, and how fast to send it: the daemon's model of
ArduPlane guided flight.

A plane given a DO_REPOSITION target flies towards it at its airspeed, turning no faster than a
coordinated turn at its bank limit, and on arrival (within WP_RADIUS, or when the point passes
close abeam, inside its turn circle) loiters clockwise around it on the tightest circle it can fly
(the requested radius, never below ~1.05 x the minimum turn radius). A DO_CHANGE_SPEED moves its
airspeed toward the new value at a bounded acceleration. The daemon predicts that path for every
candidate guided target, so the safety envelope can judge the path the plane will really fly
(turn radius, loiter circle, lag) rather than the cell centres the planner thinks in::

    turn_rate = g * tan(bank_limit) / V            (5.6 deg/s at 100 m/s, 45 deg)
    min_turn_radius = V**2 / (g * tan(bank_limit))  (1.02 km at 100 m/s, 2.29 km at 150 m/s)

Leg timing. The paper's grid moves every UAV one cell per decision step, a diagonal cell too, so
its model flies 1 km legs at v and 1.41 km legs at sqrt(2) v (design.md, "mission grid"). With
``leg_timing`` the daemon asks each plane for the airspeed that brings it to its next cell centre
at the next decision instant (``leg_speed_mps``), within [min_speed_mps, max_speed_mps]; a plane
that fell behind (a turn, an envelope override) catches up. Without it every plane flies its
cruise speed and falls behind the grid on diagonals (~245 km flown in 250 steps instead of the
grid's ~310 km).

Vectorised over rows (UAVs x candidates). Positions in km in the mission frame (x east, y
north); courses in radians counter-clockwise from east, as the planner's grid headings.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

GRAVITY_MPS2 = 9.80665


@dataclass(frozen=True)
class PlaneModel:
    """What the daemon assumes of every plane (ArduPlane parameter names in the comments)."""

    speed_mps: float = 100.0  # AIRSPEED_CRUISE: the scenario's UAV speed
    bank_limit_deg: float = 45.0  # ROLL_LIMIT_DEG (ArduPlane's default)
    capture_radius_m: float = 90.0  # WP_RADIUS
    loiter_radius_factor: float = 1.05  # tightest loiter flown, in minimum turn radii
    #: WP_LOITER_RAD: the loiter radius asked for (DO_REPOSITION param3 = 0 takes it); flown
    #: unless the plane cannot turn that tight (the simulator's 60 m, ArduPlane SITL's 80 m)
    wp_loiter_radius_m: float = 60.0
    loiter_gain: float = 2.0  # how hard the loiter path converges onto its circle
    #: slowest airspeed asked for when timing legs: cruise, since a slower plane turns more than
    #: phi_max in a step (with 75 m/s allowed, 14 turn breaches in one paper-10uav mission)
    min_speed_mps: float = 100.0
    max_speed_mps: float = 150.0  # fastest (<= AIRSPEED_MAX): sqrt(2) v and room to catch up
    #: AIRSPEED_MIN: the slowest the autopilot flies in its automatic modes (ArduPilot sets it
    #: 20 % above the stall); a plane whose home is near another's circles it this slowly
    #: (``home_circles.home_circle_speeds``)
    slowest_mps: float = 100.0
    accel_mps2: float = 5.0  # how fast the airspeed follows a DO_CHANGE_SPEED
    #: each UAV's own leg timing range (low, high) m/s, by UAV index, from its own airframe
    #: (a mixed fleet: a PX4 SIH plane tops out at 13.5 m/s beside an ArduPlane's 30); empty:
    #: every UAV flies [min_speed_mps, max_speed_mps]
    uav_speed_ranges_mps: tuple[tuple[float, float], ...] = ()
    #: each UAV's own turn limits (bank limit deg, loiter radius asked m, acceptance radius m),
    #: by UAV index, for a fleet of more than one airframe; empty: every UAV flies the fields
    #: above (the fleet's most restrictive where it is mixed)
    uav_turn_limits: tuple[tuple[float, float, float], ...] = ()

    def rows(self, uavs: np.ndarray) -> PlaneModel:
        """This model for rows of planes, ``uavs`` (M,) the UAV of each row: with each row's
        own bank limit, loiter and acceptance radius (arrays over the rows) where the UAVs
        have turn limits of their own, else this model itself."""
        if not self.uav_turn_limits:
            return self
        limits = np.asarray(self.uav_turn_limits, dtype=float)[np.asarray(uavs, dtype=int)]
        return replace(
            self,
            bank_limit_deg=limits[:, 0],
            wp_loiter_radius_m=limits[:, 1],
            capture_radius_m=limits[:, 2],
            uav_turn_limits=(),
        )

    def speed_range_mps(self, uavs: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The leg timing range (low, high) of each row's UAV ``uavs`` (indices), or the
        fleet's when no UAV is given or the UAVs have no ranges of their own."""
        if uavs is None or not self.uav_speed_ranges_mps:
            return np.asarray(self.min_speed_mps), np.asarray(self.max_speed_mps)
        ranges = np.asarray(self.uav_speed_ranges_mps, dtype=float).reshape(-1, 2)
        rows = ranges[np.asarray(uavs, dtype=int)]
        return rows[:, 0], rows[:, 1]

    @property
    def fastest_leg_mps(self) -> float:
        """The fastest airspeed any UAV is asked for when timing legs."""
        own = (high for _, high in self.uav_speed_ranges_mps)
        return max(own, default=self.max_speed_mps)

    def min_turn_radius_km(self, speed_mps: np.ndarray | float | None = None) -> np.ndarray:
        v = self.speed_mps if speed_mps is None else np.asarray(speed_mps, dtype=float)
        return v**2 / (GRAVITY_MPS2 * np.tan(np.radians(self.bank_limit_deg))) / 1e3

    def turn_rate_radps(self, speed_mps: np.ndarray | float | None = None) -> np.ndarray:
        v = self.speed_mps if speed_mps is None else np.asarray(speed_mps, dtype=float)
        return GRAVITY_MPS2 * np.tan(np.radians(self.bank_limit_deg)) / np.maximum(v, 1.0)

    def loiter_radius_km(self, speed_mps: np.ndarray | float | None = None) -> np.ndarray:
        """The circle a plane flies around a loiter point: WP_LOITER_RAD, or the tightest it
        can fly at that airspeed when that is wider."""
        tightest = self.loiter_radius_factor * self.min_turn_radius_km(speed_mps)
        return np.maximum(tightest, abs(self.wp_loiter_radius_m) / 1000.0)

    def fastest_for_loiter_radius_mps(self, radius_km: np.ndarray | float) -> np.ndarray:
        """The fastest airspeed whose loiter circle (``loiter_radius_km``) is no wider than
        ``radius_km``: the inverse of the tightest circle; 0 where WP_LOITER_RAD alone is
        wider (no airspeed flies a circle that small)."""
        r_m = np.asarray(radius_km, dtype=float) * 1e3
        turn = GRAVITY_MPS2 * np.tan(np.radians(self.bank_limit_deg)) / self.loiter_radius_factor
        fastest = np.sqrt(np.maximum(r_m, 0.0) * turn)
        return np.where(r_m >= abs(self.wp_loiter_radius_m), fastest, 0.0)

    def loiter_reach_km(self, speed_mps: np.ndarray | float | None = None) -> np.ndarray:
        """How far from a loiter point a plane strays when it arrives there: a loiter diameter.
        It flies straight at the point, passes it, and only then turns onto its circle (the
        simulator: 2.04 km from the point at 100 m/s, its circle being 1.07 km; a GCS outage
        took planes whose circles kept the margin into threat zones, issue 12)."""
        return 2.0 * self.loiter_radius_km(speed_mps)


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles (rad) into [-pi, pi)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


def leg_speed_mps(
    model: PlaneModel,
    position_km: np.ndarray,
    from_km: np.ndarray,
    to_km: np.ndarray,
    speed_now_mps: np.ndarray,
    step_s: float,
    uavs: np.ndarray | None = None,
) -> np.ndarray:
    """Airspeed (M,) to command so that planes at ``position_km`` (M, 2), flying
    ``speed_now_mps``, reach the centre ``to_km`` of the leg ``from_km`` -> ``to_km`` in
    ``step_s``: the distance still to go along the leg (plus the cross-track offset), and the
    acceleration limit on the way to the new speed, solved for the commanded speed ``v``::

        flown in step_s = v T - (v - v0) |v - v0| / (2 a) = distance to go

    Clipped to [min_speed_mps, max_speed_mps], or to each row's own UAV's range when ``uavs``
    (M,) names the UAV of each row (``PlaneModel.speed_range_mps``); a plane ahead of its
    schedule slows down, one behind catches up, and a leg of zero length (circle here) is flown
    at cruise speed."""
    p = np.asarray(position_km, dtype=float).reshape(-1, 2)
    a_km = np.asarray(from_km, dtype=float).reshape(-1, 2)
    b_km = np.asarray(to_km, dtype=float).reshape(-1, 2)
    v0 = np.broadcast_to(np.asarray(speed_now_mps, dtype=float), (len(p),))
    leg = b_km - a_km
    length = np.hypot(leg[:, 0], leg[:, 1])
    unit = leg / np.maximum(length, 1e-9)[:, None]
    to_go = b_km - p
    along = np.einsum("ij,ij->i", to_go, unit)
    cross = unit[:, 0] * to_go[:, 1] - unit[:, 1] * to_go[:, 0]
    distance_m = np.where(along > 0, np.hypot(along, cross), 0.0) * 1e3
    t, acc = float(step_s), float(model.accel_mps2)
    excess = distance_m - v0 * t  # beyond what the current speed covers
    reachable = acc * t * t / 2
    root = np.sqrt(np.maximum(acc * acc * t * t - 2 * acc * np.abs(excess), 0.0))
    change = np.where(np.abs(excess) < reachable, acc * t - root, np.inf)
    wanted = v0 + np.sign(excess) * change
    low, high = model.speed_range_mps(uavs)
    speed = np.clip(np.nan_to_num(wanted), low, high)
    return np.where(length > 1e-9, speed, model.speed_mps)


def predict_paths(
    model: PlaneModel,
    xy_km: np.ndarray,
    course_rad: np.ndarray,
    aim_km: np.ndarray,
    horizon_s: float,
    sample_s: float = 1.0,
    dt_s: float = 0.2,
    speed_mps: np.ndarray | None = None,
    commanded_mps: np.ndarray | None = None,
    turn_sign: np.ndarray | None = None,
) -> np.ndarray:
    """Positions (M, S + 1, 2) every ``sample_s`` from now (index 0) to ``horizon_s`` of planes
    at ``xy_km`` (M, 2) flying ``course_rad`` (M,) at ``speed_mps`` (M,; default cruise) after
    being sent to ``aim_km`` (M, 2) and, when given, to the airspeed ``commanded_mps`` (M,).
    A plane turns the shorter way onto its aim; with ``turn_sign`` (M,; +1 left, -1 right,
    0 the shorter way) the given way, for as long as the aim is more than 90 degrees off its
    nose (a turn about is near 180 degrees either way, and which way an autopilot takes it
    depends on its bank at the instant the command takes hold)."""
    p = np.array(xy_km, dtype=float, copy=True).reshape(-1, 2)
    course = np.array(course_rad, dtype=float, copy=True).reshape(-1)
    aim = np.asarray(aim_km, dtype=float).reshape(-1, 2)
    m = len(p)
    speed = np.array(
        np.broadcast_to(model.speed_mps if speed_mps is None else speed_mps, (m,)), dtype=float
    )
    target = speed.copy() if commanded_mps is None else np.broadcast_to(commanded_mps, (m,))
    max_dv = model.accel_mps2 * dt_s
    capture_km = model.capture_radius_m / 1000.0
    orbiting = np.zeros(m, dtype=bool)
    per_sample = max(1, round(sample_s / dt_s))
    samples = max(1, round(horizon_s / sample_s))
    out = np.empty((m, samples + 1, 2))
    out[:, 0] = p
    for k in range(samples * per_sample):
        before = speed
        speed = speed + np.clip(target - speed, -max_dv, max_dv)
        step_km = 0.5 * (before + speed) * dt_s / 1000.0
        max_turn = model.turn_rate_radps(speed) * dt_s
        d = aim - p
        dist = np.hypot(d[:, 0], d[:, 1])
        to_aim = np.arctan2(d[:, 1], d[:, 0])
        desired = to_aim.copy()
        if orbiting.any():
            # clockwise loiter: tangent = bearing from the centre - 90 deg, steered onto the circle
            loiter_km = model.loiter_radius_km(speed)[orbiting]
            from_centre = to_aim[orbiting] + np.pi
            correction = np.arctan(model.loiter_gain * (dist[orbiting] - loiter_km) / loiter_km)
            desired[orbiting] = from_centre - (np.pi / 2 + correction)
        error = wrap_angle(desired - course)
        if turn_sign is not None:
            forced = (turn_sign != 0) & ~orbiting & (np.abs(error) > np.pi / 2)
            error = np.where(forced & (error * turn_sign < 0), error + 2 * np.pi * turn_sign, error)
        turn = np.clip(error, -max_turn, max_turn)
        mid = course + 0.5 * turn
        course = course + turn
        p = p + step_km[:, None] * np.stack([np.cos(mid), np.sin(mid)], axis=1)
        if not orbiting.all():
            d = aim - p
            dist = np.hypot(d[:, 0], d[:, 1])
            ahead = np.cos(course) * d[:, 0] + np.sin(course) * d[:, 1]
            passed_km = 2.0 * model.min_turn_radius_km(speed)
            orbiting |= (dist <= capture_km) | ((ahead < 0) & (dist < passed_km))
        if (k + 1) % per_sample == 0:
            out[:, (k + 1) // per_sample] = p
    return out


def fly_on(
    plane: PlaneModel,
    positions_km: np.ndarray,
    courses_rad: np.ndarray,
    speeds_mps: np.ndarray,
    aims_km: np.ndarray,
    stale_s: np.ndarray,
) -> np.ndarray:
    """Each plane whose latest report is ``stale_s`` old (at least 1 s) and that has a target
    (``aims_km`` finite) flown on toward it for that long, in place (``positions_km`` and
    ``courses_rad``); returns the whole seconds each was flown on (0 for the others)."""
    flown = np.zeros(len(positions_km))
    late = np.flatnonzero((stale_s >= 1.0) & np.all(np.isfinite(aims_km), axis=1))
    if len(late):
        ahead = predict_paths(
            plane, positions_km[late], courses_rad[late], aims_km[late],
            float(stale_s[late].max()), speed_mps=speeds_mps[late],
        )  # fmt: skip
        at = np.round(stale_s[late]).astype(int)
        here, before = ahead[np.arange(len(late)), at], ahead[np.arange(len(late)), at - 1]
        positions_km[late] = here
        courses_rad[late] = np.arctan2(here[:, 1] - before[:, 1], here[:, 0] - before[:, 0])
        flown[late] = at
    return flown
