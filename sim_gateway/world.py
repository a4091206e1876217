"""The ground truth the swarm searches: moving targets, threat zones and a noisy sensor.

One implementation serves the in-process offline runs and the MAVLink simulator. Ground truth
never leaves this module except as what a real sensor or a real engagement would report.

Target motion, by kind (section 3.1 of the paper; one decision step is ``dt``):

============== ================================ =========================================
kind           before arrival (t0, eqs 10-14)   during the mission (eqs 20-22)
============== ================================ =========================================
unknown_pos.   stationary at its Table 1 spot    stationary
known_position N(x*, delta_0^2) + Wiener(t0)     Wiener: N(0, delta_e^2 dt) per axis
known_speed    N(x*, delta_0^2) + v t0, random  v dt along a heading drawn anew each step
               fixed heading                     (the ring model of eq 21)
known_velocity N(x*, delta_0^2) + v t0 heading   v dt along its heading
============== ================================ =========================================

At the area's edge a target is reflected back inside and its heading mirrored.
"""

from __future__ import annotations

import numpy as np

from planner.engagement import EngagementOutcome
from planner.grid import Grid
from planner.scenario import Scenario
from planner.sensor_model import SensorReport, detection_probability

KIND_CODES = {"unknown_position": 0, "known_position": 1, "known_speed": 2, "known_velocity": 3}


def reflect_into(positions: np.ndarray, headings: np.ndarray, size: tuple[float, float]) -> None:
    """Reflect points that left ``[0, size)`` back inside and mirror their headings, in place."""
    for axis, limit in enumerate(size):
        low = positions[:, axis] < 0
        high = positions[:, axis] >= limit
        positions[low, axis] = -positions[low, axis]
        positions[high, axis] = 2 * limit - positions[high, axis] - 1e-9
        flipped = low | high
        if axis == 0:
            headings[flipped] = np.pi - headings[flipped]
        else:
            headings[flipped] = -headings[flipped]
        np.clip(positions[:, axis], 0, limit - 1e-9, out=positions[:, axis])


class World:
    """Ground-truth targets and threats of a scenario, with a seeded random stream."""

    def __init__(self, scenario: Scenario, seed: int) -> None:
        cfg = scenario.config
        self.scenario = scenario
        self.config = cfg
        self.grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
        self.rng = np.random.default_rng([seed, 0x3D])
        specs = scenario.targets
        self.target_ids = np.array([t.id for t in specs], dtype=np.int64)
        self.values = np.array([t.value for t in specs], dtype=float)
        self.kinds = np.array([KIND_CODES[t.kind] for t in specs], dtype=np.int64)
        self.speeds_kmps = np.array([t.speed_mps for t in specs], dtype=float) / 1000.0
        self.headings = np.array([t.heading_rad for t in specs], dtype=float)
        self.alive = np.ones(len(specs), dtype=bool)
        self.engaged_step = np.full(len(specs), -1, dtype=np.int64)
        self.positions = self._initial_positions()
        # the sensor's footprint: offsets (K, 2), their reach, and offset -> index in offsets
        self.footprint = self.grid.disc_offsets(cfg.detection_radius_km)
        self.footprint_reach = reach = int(np.abs(self.footprint).max())
        self.footprint_slot = np.full((2 * reach + 1, 2 * reach + 1), -1)
        self.footprint_slot[self.footprint[:, 0] + reach, self.footprint[:, 1] + reach] = np.arange(
            len(self.footprint)
        )
        self.time_s = 0.0

    # ------------------------------------------------------------------ targets

    def _initial_positions(self) -> np.ndarray:
        cfg, rng = self.config, self.rng
        known = np.array([[t.x_km, t.y_km] for t in self.scenario.targets], dtype=float)
        moving = self.kinds != KIND_CODES["unknown_position"]
        pos = known.copy()
        pos[moving] += rng.normal(0.0, cfg.delta_0_km, size=(int(moving.sum()), 2))
        wiener = self.kinds == KIND_CODES["known_position"]
        pos[wiener] += rng.normal(
            0.0, cfg.delta_e_km_per_sqrt_s * np.sqrt(cfg.t0_s), size=(int(wiener.sum()), 2)
        )
        ring = self.kinds == KIND_CODES["known_speed"]
        self.headings[ring] = rng.uniform(0, 2 * np.pi, size=int(ring.sum()))
        shifted = ring | (self.kinds == KIND_CODES["known_velocity"])
        offset = self.speeds_kmps * cfg.t0_s
        pos[shifted, 0] += offset[shifted] * np.cos(self.headings[shifted])
        pos[shifted, 1] += offset[shifted] * np.sin(self.headings[shifted])
        reflect_into(pos, self.headings, self.config.area_km)
        return pos

    def step(self, dt_s: float | None = None) -> None:
        """Move every live target over one decision period (eqs 20-22 as ground truth)."""
        dt = self.config.step_s if dt_s is None else dt_s
        rng = self.rng
        wiener = self.kinds == KIND_CODES["known_position"]
        sigma = self.config.delta_e_km_per_sqrt_s * np.sqrt(dt)
        self.positions[wiener] += rng.normal(0.0, sigma, size=(int(wiener.sum()), 2))
        ring = self.kinds == KIND_CODES["known_speed"]
        self.headings[ring] = rng.uniform(0, 2 * np.pi, size=int(ring.sum()))
        moving = ring | (self.kinds == KIND_CODES["known_velocity"])
        dist = self.speeds_kmps[moving] * dt
        self.positions[moving, 0] += dist * np.cos(self.headings[moving])
        self.positions[moving, 1] += dist * np.sin(self.headings[moving])
        reflect_into(self.positions, self.headings, self.config.area_km)
        self.time_s += dt

    # ------------------------------------------------------------------ sensor

    def sense(self, uav_xy_km: np.ndarray) -> list[SensorReport]:
        """One look of each UAV's sensor (eq 17): every cell of the footprint of radius R around
        the UAV reports b = 1 with probability p(b=1|d) if a live target is in it (d = distance
        UAV-target), and with the cell's false alarm probability otherwise (``cell_false_alarm``:
        P_F for the whole look by default, eq 17's b_k being one bit for the FOV)."""
        cfg, grid = self.config, self.grid
        uav_xy_km = np.asarray(uav_xy_km, dtype=float).reshape(-1, 2)
        uav_cells = grid.cell_of(uav_xy_km)
        cells = uav_cells[:, None, :] + self.footprint[None]  # (N, K, 2)
        p_b1 = np.full(cells.shape[:2], cfg.cell_false_alarm)
        live = np.flatnonzero(self.alive)
        if live.size:
            uav, target, k = self.footprint_hits(uav_cells, live)
            d = np.hypot(*(self.positions[live[target]] - uav_xy_km[uav]).T)
            # several targets in one cell: the nearest one decides the bit's probability
            np.maximum.at(p_b1, (uav, k), detection_probability(d, cfg))  # >= the floor
        detected = self.rng.random(p_b1.shape) < p_b1
        inside = grid.inside(cells)
        whole = inside.all(axis=1).tolist()  # footprint fully inside: no selection to copy
        return [
            SensorReport(cells[i], detected[i])
            if whole[i]
            else SensorReport(cells[i][inside[i]], detected[i][inside[i]])
            for i in range(len(cells))
        ]

    def footprint_hits(
        self, uav_cells: np.ndarray, targets: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which of the ``targets`` (indices) lie in which UAV's sensor footprint: arrays
        ``(uav, m, k)``, target ``targets[m]`` is in footprint cell ``k`` of UAV ``uav`` (whose
        cell is ``uav_cells[uav]``). The one rule of "inside a footprint" for the sensor and
        the target account (``sim_gateway.target_account``)."""
        reach, slot = self.footprint_reach, self.footprint_slot
        rel = self.grid.cell_of(self.positions[targets])[None, :, :] - uav_cells[:, None, :]
        near = (np.abs(rel) <= reach).all(axis=2)  # (N, T)
        uav, target = np.nonzero(near)
        k = slot[rel[uav, target, 0] + reach, rel[uav, target, 1] + reach]
        hit = k >= 0
        return uav[hit], target[hit], k[hit]

    # ------------------------------------------------------------------ engagement

    def engage(self, xy_km: np.ndarray, step: int = -1) -> EngagementOutcome:
        """Resolve an engagement request at a UAV position against ground truth: the nearest live
        target within the engage radius is serviced (and leaves the world)."""
        live = np.flatnonzero(self.alive)
        if live.size == 0:
            return EngagementOutcome(False)
        d = np.hypot(*(self.positions[live] - np.asarray(xy_km, float)).T)
        k = int(np.argmin(d))
        if d[k] > self.config.engage_radius_km:
            return EngagementOutcome(False)
        index = live[k]
        self.alive[index] = False
        self.engaged_step[index] = step
        return EngagementOutcome(True, int(self.target_ids[index]), float(self.values[index]))
