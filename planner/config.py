"""One typed configuration for the HAPF-ACO planner, with the paper's values as defaults.

Every number the paper fixes (section 4.1, Table 2) is a default here; every choice the
paper leaves open is a named field with the reason for its default in ``docs/parameters.md``.
Units are in the field names: ``_km``, ``_s``, ``_mps``, ``_deg``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

from planner.errors import UserError
from planner.grid import Grid


class ConfigError(UserError, ValueError):
    """A configuration value is missing, of the wrong type or out of range."""


#: Fields whose default is infinite, meaning "no limit": a mapping (a scenario file) leaves
#: them out for that, and any value it gives must be finite (a typo such as ``1e400`` is infinity
#: to TOML and would silently lift the limit). Name -> how to get no limit.
UNBOUNDED = {"max_range_km": "leave max_range_km out for no range limit"}


@dataclass(frozen=True)
class PlannerConfig:
    """All parameters of the planner and the world it is evaluated in.

    Paper symbol -> field (see docs/symbols.md for the full table).
    """

    # --- mission grid (section 2.1, 4.1) ---
    grid_nx: int = 100  # N_x, cells along x (east)
    grid_ny: int = 100  # N_y, cells along y (north)
    cell_km: float = 1.0  # L_x = L_y, cell side
    step_s: float = 10.0  # decision period (one cell per step at 100 m/s)
    speed_mps: float = 100.0  # v, UAV airspeed
    max_turn_deg: float = 45.0  # phi_max, per decision step

    # --- sensor (eqs 17-18, section 4.1) ---
    detection_radius_km: float = 3.0  # R, sensor footprint radius; also d_out of eq 17
    sensor_d_in_km: float = 2.0  # d_in of eq 17 (open in the paper)
    p_detect: float = 0.9  # P_D
    p_false: float = 0.1  # P_F
    #: P_F is the false alarm probability of a whole look, as eq 17's b_k is one bit for the
    #: FOV ("no target in the sensor field of view"); each footprint cell then false-alarms with
    #: ``cell_false_alarm``, so that a look false-alarms somewhere with probability P_F. False:
    #: every cell false-alarms with P_F (a look of K = 29 cells then does 95 % of the time)
    false_alarm_per_look: bool = True
    tpm_decay_tau: float = 1.0  # tau of eq 18 for cells outside the view (open; 1 = no decay)
    confirm_threshold: float = 0.6  # probability within the engage radius that confirms (open)
    pursue_threshold: float = (
        0.05  # existence probability worth flying back for a closer look (open)
    )
    pursue_keep_threshold: float = 0.01  # ... below which a pursued suspect is ruled out (open)
    pursue_max_steps: int = 16  # steps a suspect below pursue_threshold is kept at most (open)
    pursue_range_km: float = 6.0  # farthest cell a UAV flies to for a look or an engagement (open)
    engage_radius_km: float = 1.0  # attack (engagement) radius

    # --- target priors and motion (eqs 10-14, 19-22) ---
    delta_0_km: float = 5.0  # delta_0, std of the prior position error
    # delta_e, Wiener diffusion: the paper's "2" read as 200 m per sqrt(decision step of 10 s)
    delta_e_km_per_sqrt_s: float = 0.2 / math.sqrt(10.0)
    t0_s: float = 50.0  # t_0, delay between tasking and arrival

    # --- dynamic topology (eqs 1-3) ---
    n_topo: int = 5  # expected number of neighbours
    sensing_radius_km: float = 50.0  # R_sen, upper bound of r_coor
    topology_rate: float = 0.1  # k in eq 2, 0 < k < 1
    coop_radius_init_km: float = 20.0  # r_coor at start
    coop_radius_min_km: float = 3.0  # floor of r_coor (open)
    info_max_age_steps: int = 20  # how long a neighbour's last state is predicted forward (eq 31)

    # --- artificial potential field (eqs 23-27) ---
    k_att: float = 1.0  # k_att of eq 23 on the TPM (existence probability per cell)
    k_rep: float = 1.0  # k_rep of eq 25
    threat_margin_km: float = 0.0  # d_0 = R_t + margin, the distance that must never be crossed
    morse_b: float = 1.0  # b of eqs 26-27
    morse_c_km: float = 1.0  # c of eqs 26-27
    morse_r0_km: float = 0.5  # ||x_ij||_min of eq 26: singular distance, below d_min
    uav_repulsion_range_km: float = 5.0  # d_max^v of eq 26
    min_separation_km: float = 1.0  # d_min of C_c
    separation_sense_km: float = 3.0  # UAVs this close are always seen for collision avoidance

    # --- pheromone (eqs 28-34, Table 2) ---
    tau_min: float = 0.1  # lower clamp of eq 29 (open)
    tau_max: float = 1.0  # upper clamp of eq 29 (open); maps start here
    local_decrement: float = 0.1  # delta tau_l0 (Table 2)
    global_increment: float = 15.0  # delta tau_g0 (Table 2)
    uncertainty_factor: float = 0.02  # F of eq 34 (Table 2)
    global_update_period_steps: int = 50  # period of eq 34 (open)

    # --- transition rules (eqs 35-37, Table 2) ---
    alpha: float = 1.0  # pheromone exponent
    beta: float = 3.0  # heuristic exponent
    q0: float = 0.5  # exploitation threshold of eq 37 (open)
    env_perception_lambda: float = 0.5  # lambda of eq 35 (open)
    force_floor: float = 1e-6  # below this F_max the force carries no direction
    escape_steps: int = 10  # N_t
    eta_floor: float = 0.05  # keeps eta > 0 where no cell is new
    eta_tpm_weight: float = 1.0  # weight of TPM mass in the heuristic (open)
    eta_lookahead_steps: int = (
        8  # straight steps ahead whose footprints count as coverage gain (open)
    )
    eta_lookahead_weight: float = 1.0  # weight of that look-ahead unsearched share in eta (open)
    eta_lookahead_discount: float = 0.85  # weight of each further step ahead (open)
    # far attraction: eq 23's field smoothed over far_length_km, read far_lookahead_steps ahead
    far_weight: float = 0.0  # weight in eta of the pull toward distant TPM mass (open)
    far_length_km: float = 15.0  # decay length of that pull (open)
    far_lookahead_steps: int = 8  # where along each candidate's heading it is read (open)
    far_block_cells: int = 10  # block side of the TPM mass it sums (open)
    far_refresh_steps: int = 5  # how often the block masses are recomputed (open)

    # --- range constraint C_r (eqs 35, 37) ---
    max_range_km: float = math.inf  # L_max
    return_reserve_km: float = 4.0  # kept back for turns on the way home (open)
    return_margin_km: float = 6.0  # slack below which the return term decides (open)
    # --- home by mission end (section 4.3: UAVs back at their start at the last step) ---
    home_by_end: bool = False  # plan C_r so every UAV is home at the scenario's last step
    home_reserve_steps: int = 3  # steps kept back for detours on the way home (open)
    home_margin_steps: int = 0  # time slack below which the return term decides (open)
    #: clearance (km, beyond R_t) of the way home that C_r counts (hops and km home); 0: the
    #: same as the moves'. A flown plane keeps a wider berth (the daemon sets its own, open)
    home_path_margin_km: float = 0.0

    # --- seeds for the parts of the run that are random ---
    seed: int = 0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.type in ("int",) and not isinstance(value, int | bool):
                raise ConfigError(f"parameter {f.name!r} must be an integer, got {value!r}")
            if f.type in ("bool",) and not isinstance(value, bool):
                raise ConfigError(f"parameter {f.name!r} must be true or false, got {value!r}")
            if f.type in ("float",) and not isinstance(value, int | float):
                raise ConfigError(f"parameter {f.name!r} must be a number, got {value!r}")
            if isinstance(value, float) and math.isnan(value):
                raise ConfigError(f"parameter {f.name!r} is NaN; give a number")
            if isinstance(value, float) and math.isinf(value) and f.name not in UNBOUNDED:
                raise ConfigError(f"parameter {f.name!r} is infinite; give a finite number")
        positive = [
            "grid_nx",
            "grid_ny",
            "cell_km",
            "step_s",
            "speed_mps",
            "max_turn_deg",
            "detection_radius_km",
            "engage_radius_km",
            "pursue_range_km",
            "n_topo",
            "sensing_radius_km",
            "coop_radius_init_km",
            "morse_c_km",
            "min_separation_km",
            "tau_max",
            "global_update_period_steps",
            "escape_steps",
            "far_length_km",
            "far_block_cells",
            "far_refresh_steps",
            "max_range_km",
        ]
        for name in positive:
            if getattr(self, name) <= 0:
                raise ConfigError(f"parameter {name!r} must be > 0, got {getattr(self, name)!r}")
        probabilities = (
            "p_detect p_false tpm_decay_tau confirm_threshold pursue_threshold"
            " pursue_keep_threshold q0 env_perception_lambda"
        )
        for name in probabilities.split():
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(
                    f"parameter {name!r} must be in [0, 1], got {getattr(self, name)}"
                )
        if self.p_detect <= self.p_false:
            raise ConfigError("p_detect must be larger than p_false, or the sensor tells nothing")
        if not 0 < self.sensor_d_in_km < self.detection_radius_km:
            raise ConfigError("sensor_d_in_km must be in (0, detection_radius_km)")
        if not 0 < self.topology_rate < 1:
            raise ConfigError("topology_rate (k of eq 2) must be in (0, 1)")
        if not 0 < self.tau_min < self.tau_max:
            raise ConfigError("need 0 < tau_min < tau_max for the pheromone clamp (eq 29)")
        if not 0 <= self.morse_r0_km < self.min_separation_km:
            raise ConfigError("morse_r0_km must be in [0, min_separation_km)")
        if self.home_path_margin_km < 0:
            raise ConfigError("home_path_margin_km must be >= 0 (0: the moves' own margin)")
        if self.max_turn_deg < 45:
            raise ConfigError(
                "max_turn_deg below 45 leaves only straight flight on an 8-heading grid"
            )

    # --- derived quantities ---
    @property
    def step_km(self) -> float:
        """Distance flown in one decision step."""
        return self.speed_mps * self.step_s / 1000.0

    @cached_property
    def footprint_cells(self) -> int:
        """K: cells whose centres lie within the detection radius R of a cell centre."""
        return len(Grid(cell_km=self.cell_km).disc_offsets(self.detection_radius_km))

    @cached_property
    def cell_false_alarm(self) -> float:
        """Probability that one footprint cell without a target reports b = 1 (eqs 17-18 per
        cell): ``1 - (1 - P_F)^(1/K)`` when P_F is a look's (``false_alarm_per_look``), so
        that the K cells of a look false-alarm with probability P_F together; else P_F."""
        if not self.false_alarm_per_look:
            return self.p_false
        return 1.0 - (1.0 - self.p_false) ** (1.0 / self.footprint_cells)

    @property
    def area_km(self) -> tuple[float, float]:
        return (self.grid_nx * self.cell_km, self.grid_ny * self.cell_km)

    def replace(self, **changes: Any) -> PlannerConfig:
        return dataclasses.replace(self, **changes)

    def changed_from(self, base: PlannerConfig) -> dict[str, Any]:
        """The fields whose value differs from ``base``'s, with this configuration's values
        (a result's ``planned_with``: what a planner planned with beyond its scenario)."""
        return {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if getattr(self, f.name) != getattr(base, f.name)
        }

    @classmethod
    def from_mapping(
        cls, values: dict[str, Any], base: PlannerConfig | None = None
    ) -> PlannerConfig:
        """Build from a mapping (e.g. a scenario's ``[parameters]`` table), naming unknown keys."""
        known = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ConfigError(
                f"unknown parameter {unknown[0]!r}; known parameters are listed in"
                " docs/parameters.md"
            )
        clean: dict[str, Any] = {}
        for name, value in values.items():
            if (
                known[name].type == "float"
                and isinstance(value, int)
                and not isinstance(value, bool)
            ):
                value = float(value)
            if isinstance(value, float) and not math.isfinite(value):  # TOML inf, nan, 1e400
                fix = UNBOUNDED.get(name, "give a finite number")
                overflow = " (TOML reads inf, and numbers past 1.8e308, as infinity)"
                raise ConfigError(
                    f"parameter {name!r} must be finite, got {value!r}"
                    f"{overflow if math.isinf(value) else ''}; {fix}"
                )
            clean[name] = value
        return dataclasses.replace(base or cls(), **clean)

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


DEFAULT_CONFIG = PlannerConfig()

__all__ = ["ConfigError", "PlannerConfig", "DEFAULT_CONFIG"]
