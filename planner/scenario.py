"""Mission scenarios: the area, the swarm, the targets (Table 1), the threats (Table 3) and the
parameters, read from TOML and validated with one clear error per problem.

A scenario is data. The paper's experiments ship as built-in scenarios (``paper-2uav``,
``paper-10uav``, ``paper-20uav``); any other mission is a TOML file of the same form (see
``docs/scenarios.md``).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from planner.config import ConfigError, PlannerConfig
from planner.errors import UserError

#: The four kinds of time-sensitive target of section 3.1.1, by what the swarm knows of them.
TARGET_KINDS = ("unknown_position", "known_position", "known_speed", "known_velocity")

BUILTIN_SCENARIOS = (
    "paper-2uav", "paper-10uav", "paper-20uav", "arduplane-3uav", "px4-3uav", "swarm-100uav",
    "swarm-500uav",
)  # fmt: skip

#: Bounds that keep a scenario runnable (memory, time): the paper's grid is 10,000 cells, 250
#: steps, 20 UAVs; the built-in swarm-500uav has 500 (one MAVLink network carries at most 254
#: vehicles, so a larger swarm flies over several).
MAX_GRID_CELLS = 250_000
MAX_STEPS = 100_000
MAX_UAVS = 1000


class ScenarioError(UserError, ValueError):
    """A scenario cannot be used; the message names the problem and the fix."""


@dataclass(frozen=True)
class TargetSpec:
    """Prior knowledge of one target (Table 1). Positions in km, speed in m/s, heading in rad."""

    id: int
    kind: str
    x_km: float
    y_km: float
    value: float
    speed_mps: float = 0.0
    heading_rad: float = 0.0


@dataclass(frozen=True)
class ThreatSpec:
    """A circular threat (no-fly) zone (Table 3)."""

    x_km: float
    y_km: float
    radius_km: float


@dataclass(frozen=True)
class UavStart:
    x_km: float
    y_km: float
    heading_deg: float


@dataclass(frozen=True)
class Origin:
    """Geodetic position of the area's south-west corner (x = east, y = north)."""

    lat_deg: float = -35.363262
    lon_deg: float = 149.165237
    alt_m: float = 584.0


@dataclass(frozen=True)
class Scenario:
    name: str
    config: PlannerConfig
    targets: tuple[TargetSpec, ...]
    threats: tuple[ThreatSpec, ...]
    uav_count: int
    uav_starts: tuple[UavStart, ...] | None  # None: random starts drawn from the run's seed
    steps: int = 250
    threats_known: bool = False  # False: a threat is known once within R + R_t (section 3.2.2)
    origin: Origin = field(default_factory=Origin)
    altitude_m: float = 500.0
    description: str = ""

    def starts_for_seed(self, seed: int) -> tuple[UavStart, ...]:
        """The UAV start states of a run: the fixed ones, or random ones drawn from ``seed``."""
        if self.uav_starts is not None:
            return self.uav_starts
        return random_starts(self, np.random.default_rng([seed, 0x5747]))

    def with_config(self, **changes: Any) -> Scenario:
        from dataclasses import replace

        return replace(self, config=self.config.replace(**changes))


#: random starts stay this many cells inside the area's edge, and this far (km) beyond every
#: threat's radius plus the sensor's (``detection_radius_km``)
START_EDGE_CELLS = 4
START_THREAT_GAP_KM = 2.0


def _start_gap_km(cfg: PlannerConfig, threat: ThreatSpec) -> float:
    return threat.radius_km + cfg.detection_radius_km + START_THREAT_GAP_KM


def random_starts(scenario: Scenario, rng: np.random.Generator) -> tuple[UavStart, ...]:
    """Random start cells and headings (section 4.3) that are safe: clear of every threat by the
    sensor radius, at least two cells apart, and a few cells inside the area's edge."""
    cfg = scenario.config
    margin_cells = START_EDGE_CELLS
    starts: list[UavStart] = []
    for _ in range(10_000):
        if len(starts) == scenario.uav_count:
            break
        ix = int(rng.integers(margin_cells, cfg.grid_nx - margin_cells))
        iy = int(rng.integers(margin_cells, cfg.grid_ny - margin_cells))
        x, y = (ix + 0.5) * cfg.cell_km, (iy + 0.5) * cfg.cell_km
        heading = float(rng.integers(0, 8) * 45.0)
        clear = all(
            math.hypot(x - t.x_km, y - t.y_km) > _start_gap_km(cfg, t) for t in scenario.threats
        )
        apart = all(math.hypot(x - s.x_km, y - s.y_km) >= 2 * cfg.cell_km + 1e-9 for s in starts)
        if clear and apart:
            starts.append(UavStart(x, y, heading))
    if len(starts) < scenario.uav_count:
        raise no_room_for_starts(scenario, repr(scenario.name), len(starts))
    return tuple(starts)


def start_room(scenario: Scenario) -> tuple[int, np.ndarray]:
    """The cells random starts may take (inside the edge, clear of every threat), and per threat
    how many of the cells inside the edge it takes."""
    cfg = scenario.config
    m = START_EDGE_CELLS
    ix, iy = np.meshgrid(
        np.arange(m, max(m, cfg.grid_nx - m)), np.arange(m, max(m, cfg.grid_ny - m)), indexing="ij"
    )
    x, y = (ix + 0.5) * cfg.cell_km, (iy + 0.5) * cfg.cell_km
    taken = np.array(
        [np.hypot(x - t.x_km, y - t.y_km) <= _start_gap_km(cfg, t) for t in scenario.threats]
    ).reshape(len(scenario.threats), *x.shape)
    return int((~taken.any(axis=0)).sum()), taken.sum(axis=(1, 2))


def no_room_for_starts(scenario: Scenario, source: str, placed: int | None) -> ScenarioError:
    """The one line that says which threat leaves no room for the random starts (``placed``:
    how many the draw placed, None: before drawing) and how to fix it."""
    cfg = scenario.config
    room, taken = start_room(scenario)
    n = scenario.uav_count
    rule = (
        f"a start keeps radius_km + detection_radius_km {cfg.detection_radius_km:g} + "
        f"{START_THREAT_GAP_KM:g} km from every threat and {START_EDGE_CELLS} cells from the edge"
    )
    fix = "or give the starts as [[uavs.start]] entries"
    if not len(taken) or taken.max() == 0:
        return ScenarioError(
            f"scenario {source}: the {cfg.grid_nx} x {cfg.grid_ny} cell area has room for "
            f"{room} of the {n} random UAV starts ({rule}); give fewer UAVs, a larger area, {fix}"
        )
    k = int(np.argmax(taken))
    t = scenario.threats[k]
    others = int((taken > 0).sum()) - 1
    who = f"threats[{k}] (centre ({t.x_km:g}, {t.y_km:g}) km, radius_km {t.radius_km:g})"
    if others:
        who += f" and {others} other threat{'s' if others > 1 else ''}"
    left = f"room for {room}" if placed is None else f"room for {placed} (two cells apart)"
    return ScenarioError(
        f"scenario {source}: {who} leave{'' if others else 's'} {left} of the {n} random UAV "
        f"starts ({rule}); make radius_km smaller, give fewer UAVs, {fix}"
    )


# ----------------------------------------------------------------------------- parsing


def _where(source: str, path: str) -> str:
    return f"scenario {source}: {path}"


def _number(table: dict, key: str, source: str, path: str, default: Any = None) -> float:
    if key not in table:
        if default is None:
            raise ScenarioError(f"{_where(source, path + '.' + key)} is missing; add it")
        return default
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ScenarioError(
            f"{_where(source, path + '.' + key)} must be a number,"
            f" got {type(value).__name__} {value!r}"
        )
    if math.isnan(value) or math.isinf(value):
        raise ScenarioError(f"{_where(source, path + '.' + key)} must be finite, got {value!r}")
    return float(value)


def _table(doc: dict, key: str, source: str, default: Any) -> Any:
    value = doc.get(key, default)
    if not isinstance(value, type(default)):
        raise ScenarioError(
            f"scenario {source}: {key} must be a {type(default).__name__},"
            f" got {type(value).__name__}"
        )
    return value


def _check_unknown(table: dict, allowed: set[str], source: str, path: str) -> None:
    for key in table:
        if key not in allowed:
            raise ScenarioError(
                f"{_where(source, path)} has unknown key {key!r};"
                f" allowed: {', '.join(sorted(allowed))}"
            )


def parse_scenario(text: str, source: str = "<string>") -> Scenario:
    """Parse and validate a scenario from TOML text. Raises ScenarioError with a one-line
    message."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"scenario {source}: not valid TOML ({exc}); fix the syntax") from None
    return scenario_from_dict(doc, source)


def scenario_from_dict(doc: dict[str, Any], source: str = "<dict>") -> Scenario:
    """A scenario from its TOML tables (docs/scenarios.md); every fault is one ScenarioError
    line naming the entry and the fix."""
    allowed = {
        "name", "description", "steps", "threats_known", "origin", "altitude_m",
        "parameters", "uavs", "targets", "threats",
    }  # fmt: skip
    _check_unknown(doc, allowed, source, "top level")
    name = _table(doc, "name", source, Path(source).stem)
    config = _config(_table(doc, "parameters", source, {}), source)
    steps = doc.get("steps", 250)
    if isinstance(steps, bool) or not isinstance(steps, int) or not 0 < steps <= MAX_STEPS:
        raise ScenarioError(
            f"scenario {source}: steps must be a positive integer up to {MAX_STEPS}, got {steps!r}"
        )
    origin, altitude = _origin(doc, source)
    area = _Area(source, *config.area_km)
    threats = _threats(doc, area)
    targets = _targets(doc, area)
    count, starts = _uavs(doc, area, threats, config)
    threats_known = doc.get("threats_known", False)
    if not isinstance(threats_known, bool):
        raise ScenarioError(f"scenario {source}: threats_known must be true or false")
    description = doc.get("description", "")
    if not isinstance(description, str):
        raise ScenarioError(f"scenario {source}: description must be a string")
    scenario = Scenario(
        name=str(name), config=config, targets=targets, threats=threats,
        uav_count=count, uav_starts=starts, steps=steps, threats_known=threats_known,
        origin=origin, altitude_m=altitude, description=description,
    )  # fmt: skip
    if starts is None and start_room(scenario)[0] < count:
        raise no_room_for_starts(scenario, source, None)
    return scenario


def _config(params: dict[str, Any], source: str) -> PlannerConfig:
    """``[parameters]`` as the planner's configuration, within the grid size a UAV can map."""
    try:
        config = PlannerConfig.from_mapping(params)
    except ConfigError as exc:
        raise ScenarioError(f"scenario {source}: [parameters]: {exc}") from None
    except TypeError as exc:
        raise ScenarioError(f"scenario {source}: [parameters]: {exc}") from None
    if config.grid_nx * config.grid_ny > MAX_GRID_CELLS:
        raise ScenarioError(
            f"scenario {source}: [parameters] grid {config.grid_nx} x {config.grid_ny} has more "
            f"than {MAX_GRID_CELLS:,} cells (every UAV keeps maps of it); use larger cell_km"
        )
    return config


def _origin(doc: dict[str, Any], source: str) -> tuple[Origin, float]:
    """``[origin]`` (the area's south-west corner on Earth) and the flight altitude."""
    origin_t = _table(doc, "origin", source, {})
    _check_unknown(origin_t, {"lat", "lon", "alt_m"}, source, "origin")
    origin = Origin(
        _number(origin_t, "lat", source, "origin", Origin.lat_deg),
        _number(origin_t, "lon", source, "origin", Origin.lon_deg),
        _number(origin_t, "alt_m", source, "origin", Origin.alt_m),
    )
    if not -90 <= origin.lat_deg <= 90 or not -180 <= origin.lon_deg <= 180:
        raise ScenarioError(f"scenario {source}: origin lat/lon out of range; give degrees")
    altitude = _number(doc, "altitude_m", source, "top level", 500.0)
    if altitude <= 0:
        raise ScenarioError(f"scenario {source}: altitude_m must be > 0, got {altitude}")
    return origin, altitude


@dataclass(frozen=True)
class _Area:
    """The mission area of the scenario file ``source``, for placing its entries."""

    source: str
    width_km: float
    height_km: float

    def inside(self, x: float, y: float, path: str) -> None:
        if not (0 <= x < self.width_km and 0 <= y < self.height_km):
            raise ScenarioError(
                f"{_where(self.source, path)} position ({x:g}, {y:g}) km is outside the "
                f"{self.width_km:g} x {self.height_km:g} km area; move it inside"
            )


def _threats(doc: dict[str, Any], area: _Area) -> tuple[ThreatSpec, ...]:
    """``[[threats]]``: circles inside the area."""
    source, threats = area.source, []
    for i, t in enumerate(_table(doc, "threats", source, [])):
        path = f"threats[{i}]"
        if not isinstance(t, dict):
            raise ScenarioError(
                f"{_where(source, path)} must be a table with x_km, y_km, radius_km"
            )
        _check_unknown(t, {"x_km", "y_km", "radius_km", "label"}, source, path)
        threat = ThreatSpec(
            _number(t, "x_km", source, path),
            _number(t, "y_km", source, path),
            _number(t, "radius_km", source, path),
        )
        if threat.radius_km <= 0:
            raise ScenarioError(
                f"{_where(source, path)}.radius_km must be > 0, got {threat.radius_km}"
            )
        area.inside(threat.x_km, threat.y_km, path)
        threats.append(threat)
    return tuple(threats)


def _targets(doc: dict[str, Any], area: _Area) -> tuple[TargetSpec, ...]:
    """``[[targets]]``: at least one, each of a kind of Table 1 with what its kind needs."""
    source, targets = area.source, []
    seen_ids: set[int] = set()
    for i, t in enumerate(_table(doc, "targets", source, [])):
        path = f"targets[{i}]"
        if not isinstance(t, dict):
            raise ScenarioError(f"{_where(source, path)} must be a table")
        _check_unknown(
            t, {"id", "kind", "x_km", "y_km", "value", "speed_mps", "heading_rad"}, source, path
        )
        kind = t.get("kind")
        if kind not in TARGET_KINDS:
            raise ScenarioError(
                f"{_where(source, path)}.kind is {kind!r}; use one of {', '.join(TARGET_KINDS)}"
            )
        tid = t.get("id", i + 1)
        if isinstance(tid, bool) or not isinstance(tid, int) or tid in seen_ids:
            raise ScenarioError(f"{_where(source, path)}.id must be a unique integer, got {tid!r}")
        seen_ids.add(tid)
        needs_speed = kind in ("known_speed", "known_velocity")
        speed = _number(t, "speed_mps", source, path, None if needs_speed else 0.0)
        heading = _number(t, "heading_rad", source, path, None if kind == "known_velocity" else 0.0)
        value = _number(t, "value", source, path)
        if value <= 0:
            raise ScenarioError(f"{_where(source, path)}.value must be > 0, got {value}")
        if needs_speed and speed <= 0:
            raise ScenarioError(f"{_where(source, path)}.speed_mps must be > 0 for kind {kind!r}")
        if speed < 0:
            raise ScenarioError(f"{_where(source, path)}.speed_mps must be >= 0, got {speed}")
        target = TargetSpec(
            tid, kind, _number(t, "x_km", source, path), _number(t, "y_km", source, path),
            value, speed, heading,
        )  # fmt: skip
        area.inside(target.x_km, target.y_km, path)
        targets.append(target)
    if not targets:
        raise ScenarioError(f"scenario {source}: no [[targets]]; add at least one")
    return tuple(targets)


def _uavs(
    doc: dict[str, Any], area: _Area, threats: tuple[ThreatSpec, ...], config: PlannerConfig
) -> tuple[int, tuple[UavStart, ...] | None]:
    """``[uavs]``: the count and, unless the starts are random, each start (inside the area,
    outside every threat, one UAV per cell)."""
    source = area.source
    uavs = _table(doc, "uavs", source, {})
    _check_unknown(uavs, {"count", "random_start", "start"}, source, "uavs")
    starts_t = uavs.get("start")
    random_start = uavs.get("random_start", starts_t is None)
    if not isinstance(random_start, bool):
        raise ScenarioError(f"scenario {source}: uavs.random_start must be true or false")
    starts = None
    if starts_t is not None and not random_start:
        starts = _given_starts(starts_t, area, threats)
    count = uavs.get("count", len(starts) if starts else None)
    if isinstance(count, bool) or not isinstance(count, int) or not 0 < count <= MAX_UAVS:
        raise ScenarioError(
            f"scenario {source}: uavs.count must be a positive integer up to {MAX_UAVS},"
            f" got {count!r}"
        )
    if starts is not None and count != len(starts):
        raise ScenarioError(
            f"scenario {source}: uavs.count = {count} but {len(starts)} uavs.start entries;"
            " make them agree"
        )
    if starts is not None:
        cells = {(int(s.x_km // config.cell_km), int(s.y_km // config.cell_km)) for s in starts}
        if len(cells) < len(starts):
            raise ScenarioError(
                f"scenario {source}: two UAVs start in the same cell; separate them"
            )
    return count, starts


def _given_starts(
    starts_t: Any, area: _Area, threats: tuple[ThreatSpec, ...]
) -> tuple[UavStart, ...]:
    """``[[uavs.start]]``: each inside the area and outside every threat."""
    source = area.source
    if not isinstance(starts_t, list) or not starts_t:
        raise ScenarioError(f"scenario {source}: uavs.start must be a non-empty array of tables")
    parsed = []
    for i, s in enumerate(starts_t):
        path = f"uavs.start[{i}]"
        if not isinstance(s, dict):
            raise ScenarioError(f"{_where(source, path)} must be a table with x_km, y_km")
        _check_unknown(s, {"x_km", "y_km", "heading_deg"}, source, path)
        start = UavStart(
            _number(s, "x_km", source, path),
            _number(s, "y_km", source, path),
            _number(s, "heading_deg", source, path, 0.0),
        )
        area.inside(start.x_km, start.y_km, path)
        for j, threat in enumerate(threats):
            if math.hypot(start.x_km - threat.x_km, start.y_km - threat.y_km) <= threat.radius_km:
                raise ScenarioError(
                    f"{_where(source, path)} starts inside threats[{j}];"
                    " move the start or the threat"
                )
        parsed.append(start)
    return tuple(parsed)


def load_scenario(name_or_path: str | Path) -> Scenario:
    """A built-in scenario by name, or a TOML file by path."""
    text_name = str(name_or_path)
    if text_name in BUILTIN_SCENARIOS:
        text = resources.files("planner.scenarios").joinpath(f"{text_name}.toml").read_text()
        return parse_scenario(text, text_name)
    path = Path(name_or_path)
    if not path.exists():
        raise ScenarioError(
            f"scenario {text_name!r} is neither a built-in ({', '.join(BUILTIN_SCENARIOS)})"
            " nor a file"
        )
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"scenario {path}: cannot read it ({exc})") from None
    return parse_scenario(text, str(path))
