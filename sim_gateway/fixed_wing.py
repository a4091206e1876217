"""Fixed-wing kinematics for a fleet of simulated planes, vectorised over vehicles with numpy.

The model is the coordinated-turn point mass a guidance loop sees: airspeed slewed toward its
commanded value (MAV_CMD_DO_CHANGE_SPEED) at a bounded acceleration, no wind (so ground speed =
airspeed), course changed at most at the turn rate of a coordinated turn at the bank limit and
the current airspeed, altitude driven toward its target at bounded climb / sink rates::

    turn_rate = g * tan(bank_limit) / V            (5.6 deg/s at 100 m/s and 45 deg bank)
    min_turn_radius = V**2 / (g * tan(bank_limit))  (1019 m at 100 m/s and 45 deg bank)

so a plane turns 56 deg in one 10 s decision step, more than the planner's 45 deg limit.

Lateral guidance, per vehicle, is one of:

* ``HOLD``: keep the course (take-off climb, MANUAL-like modes);
* ``PURSUIT``: fly straight at a point (pure pursuit) until within the capture radius of it,
  or until it passes close abeam / behind (a plane cannot hit a point inside its turn circle);
  it then reports *arrival* and, for guided and loiter targets, switches to ``ORBIT``;
* ``ORBIT``: loiter around a point on a circle (a vector field that steers onto the circle);
  the circle's radius is the requested one but never less than 1.05 x the minimum turn
  radius, so a requested 100 m loiter at 100 m/s is flown at ~1.07 km (ArduPlane also flies
  the tightest circle it can when the requested one is too small).

Positions are local metres from the mission area's south-west corner (x east, y north);
courses are compass radians (clockwise from north). The module knows nothing of MAVLink.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GRAVITY_MPS2 = 9.80665
HOLD, PURSUIT, ORBIT = 0, 1, 2
ORBIT_RADIUS_FACTOR = 1.05  # smallest loiter radius flown, in units of the min turn radius
ORBIT_GAIN = 2.0  # vector-field convergence gain onto the loiter circle
PASSED_RADIUS_FACTOR = 2.0  # a point behind the plane within this x turn radius counts as reached
SPEED_ACCEL_MPS2 = 5.0  # airspeed change rate toward a commanded speed (about 0.5 g)


def wrap_pi(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped into [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2 * np.pi) - np.pi


@dataclass
class StepEvents:
    """What happened to which vehicle during one kinematic step (boolean masks, shape (N,))."""

    arrived: np.ndarray  # a PURSUIT target was reached this step
    climbed: np.ndarray  # the altitude target was reached this step (within 1 m)


class FleetKinematics:
    """State and motion of N fixed-wing planes; every array has one entry per vehicle."""

    def __init__(
        self,
        x_m: np.ndarray,
        y_m: np.ndarray,
        course_rad: np.ndarray,
        airspeed_mps: float = 100.0,
        bank_limit_deg: float = 45.0,
        climb_mps: float = 5.0,
        sink_mps: float = 5.0,
    ) -> None:
        n = len(x_m)
        self.n = n
        self.x_m = np.asarray(x_m, dtype=float).copy()
        self.y_m = np.asarray(y_m, dtype=float).copy()
        self.alt_m = np.zeros(n)  # above home
        self.course_rad = np.asarray(course_rad, dtype=float).copy()
        self.airspeed_mps = np.full(n, float(airspeed_mps))  # now
        self.target_airspeed_mps = self.airspeed_mps.copy()  # commanded
        self.speed_accel_mps2 = np.full(n, SPEED_ACCEL_MPS2)
        self.bank_limit_rad = np.full(n, np.radians(bank_limit_deg))
        self.climb_mps = np.full(n, float(climb_mps))
        self.sink_mps = np.full(n, float(sink_mps))
        self.airborne = np.zeros(n, dtype=bool)
        self.guidance = np.full(n, HOLD, dtype=np.int64)
        self.target_x_m = self.x_m.copy()
        self.target_y_m = self.y_m.copy()
        self.target_alt_m = np.zeros(n)
        self.capture_radius_m = np.full(n, 90.0)
        self.orbit_radius_m = np.full(n, 60.0)
        self.orbit_ccw = np.zeros(n, dtype=bool)
        self.orbit_after_arrival = np.ones(n, dtype=bool)
        self.bank_rad = np.zeros(n)  # last commanded bank angle (for ATTITUDE)
        self.climb_rate_mps = np.zeros(n)  # last vertical speed, up positive
        self.distance_flown_m = np.zeros(n)

    # ------------------------------------------------------------------ derived

    def turn_rate_radps(self) -> np.ndarray:
        """Turn rate of a coordinated turn at the bank limit."""
        return GRAVITY_MPS2 * np.tan(self.bank_limit_rad) / np.maximum(self.airspeed_mps, 1.0)

    def min_turn_radius_m(self) -> np.ndarray:
        return self.airspeed_mps**2 / (GRAVITY_MPS2 * np.tan(self.bank_limit_rad))

    # ------------------------------------------------------------------ commands

    def hold_course(self, i: int) -> None:
        self.guidance[i] = HOLD

    def fly_to(
        self,
        i: int,
        x_m: float,
        y_m: float,
        capture_radius_m: float,
        then_orbit_radius_m: float | None,
    ) -> None:
        """Pursue a point; on arrival orbit it at ``then_orbit_radius_m`` (negative: counter-
        clockwise), or, when None, keep pursuing-free course (the caller chooses the next leg)."""
        self.guidance[i] = PURSUIT
        self.target_x_m[i], self.target_y_m[i] = x_m, y_m
        self.capture_radius_m[i] = max(float(capture_radius_m), 1.0)
        if then_orbit_radius_m is None:
            self.orbit_after_arrival[i] = False
        else:
            self.orbit_after_arrival[i] = True
            self.orbit_radius_m[i] = max(abs(float(then_orbit_radius_m)), 1.0)
            self.orbit_ccw[i] = then_orbit_radius_m < 0

    def orbit(self, i: int, x_m: float, y_m: float, radius_m: float) -> None:
        """Loiter around a point now (negative radius: counter-clockwise)."""
        self.guidance[i] = ORBIT
        self.target_x_m[i], self.target_y_m[i] = x_m, y_m
        self.orbit_radius_m[i] = max(abs(float(radius_m)), 1.0)
        self.orbit_ccw[i] = radius_m < 0

    def effective_orbit_radius_m(self) -> np.ndarray:
        return np.maximum(self.orbit_radius_m, ORBIT_RADIUS_FACTOR * self.min_turn_radius_m())

    # ------------------------------------------------------------------ motion

    def desired_course(self) -> np.ndarray:
        """Course each guidance law asks for (compass radians)."""
        dx = self.target_x_m - self.x_m
        dy = self.target_y_m - self.y_m
        to_target = np.arctan2(dx, dy)
        desired = self.course_rad.copy()
        pursuit = self.guidance == PURSUIT
        desired[pursuit] = to_target[pursuit]
        orbit = self.guidance == ORBIT
        if orbit.any():
            radius = self.effective_orbit_radius_m()[orbit]
            d = np.hypot(dx[orbit], dy[orbit])
            from_centre = to_target[orbit] + np.pi
            correction = np.arctan(ORBIT_GAIN * (d - radius) / radius)
            side = np.where(self.orbit_ccw[orbit], -1.0, 1.0)
            desired[orbit] = from_centre + side * (np.pi / 2 + correction)
        return desired

    def set_airspeed(self, i: int, airspeed_mps: float, at_once: bool = False) -> None:
        """Command an airspeed: a flying plane reaches it at ``speed_accel_mps2``; one on the
        ground (or ``at_once``) has it at once."""
        self.target_airspeed_mps[i] = float(airspeed_mps)
        if at_once or not self.airborne[i]:
            self.airspeed_mps[i] = float(airspeed_mps)

    def step(self, dt_s: float) -> StepEvents:
        """Advance every airborne plane by ``dt_s`` seconds."""
        flying = self.airborne
        max_dv = self.speed_accel_mps2 * dt_s
        dv = np.clip(self.target_airspeed_mps - self.airspeed_mps, -max_dv, max_dv)
        v_before = self.airspeed_mps.copy()
        self.airspeed_mps = np.where(flying, self.airspeed_mps + dv, self.target_airspeed_mps)
        error = wrap_pi(self.desired_course() - self.course_rad)
        max_turn = self.turn_rate_radps() * dt_s
        turn = np.clip(error, -max_turn, max_turn)
        turn[~flying] = 0.0
        mid_course = self.course_rad + 0.5 * turn
        self.course_rad = np.mod(self.course_rad + turn, 2 * np.pi)
        speed = np.where(flying, 0.5 * (v_before + self.airspeed_mps), 0.0)
        self.bank_rad = np.arctan(speed * (turn / dt_s) / GRAVITY_MPS2)
        self.x_m += speed * np.sin(mid_course) * dt_s
        self.y_m += speed * np.cos(mid_course) * dt_s
        self.distance_flown_m += speed * dt_s

        dz = self.target_alt_m - self.alt_m
        vz = np.clip(dz / dt_s, -self.sink_mps, self.climb_mps)
        vz[~flying] = 0.0
        self.alt_m += vz * dt_s
        self.climb_rate_mps = vz
        climbed = flying & (np.abs(dz) > 1.0) & (np.abs(self.target_alt_m - self.alt_m) <= 1.0)

        arrived = np.zeros(self.n, dtype=bool)
        pursuit = flying & (self.guidance == PURSUIT)
        if pursuit.any():
            dx = self.target_x_m - self.x_m
            dy = self.target_y_m - self.y_m
            d = np.hypot(dx, dy)
            ahead = np.sin(self.course_rad) * dx + np.cos(self.course_rad) * dy
            passed = (ahead < 0) & (d < PASSED_RADIUS_FACTOR * self.min_turn_radius_m())
            arrived = pursuit & ((d <= self.capture_radius_m) | passed)
            to_orbit = arrived & self.orbit_after_arrival
            self.guidance[to_orbit] = ORBIT
            self.guidance[arrived & ~self.orbit_after_arrival] = HOLD
        return StepEvents(arrived=arrived, climbed=climbed)
