"""Writes the built-in scale scenarios ``swarm-100uav`` and ``swarm-500uav``
(planner/scenarios/*.toml) from the paper's 20-UAV one (section 4.3, Tables 1 and 3).

    python tools/swarm_scenarios.py [DIR]  # rewrites the two files (in DIR if given)

A 200 x 200 km area (200 x 200 cells of 1 km) made of four copies of the paper's 100 x 100 km
world, one per quadrant: 64 targets (16 of each of the four kinds) and 20 threat zones. The
UAVs start spread evenly over rings a few km inside the area's edges, each heading inwards
(the paper's starts are random inside its area; a swarm this large is launched from its
edges), clear of every threat as random starts are (``planner.scenario.START_THREAT_GAP_KM``
beyond its radius and the sensor's). Everything else is the paper's (L_max 330 km, 250
steps, home by the end).
"""

from __future__ import annotations

import math
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from planner.config import PlannerConfig  # noqa: E402
from planner.scenario import START_THREAT_GAP_KM  # noqa: E402

SCENARIOS = ROOT / "planner" / "scenarios"
SIDE_KM = 200.0
QUADRANT_KM = 100.0
#: start rings (km inside the edge) and the spacing along them: 100 UAVs take the outer ring,
#: 500 the outer two
RINGS_KM = (6.0, 12.0)


def quadrant_copies(paper: dict) -> tuple[list[dict], list[dict]]:
    """The paper's targets and threats, once in each quadrant (ids renumbered 1..64)."""
    targets, threats = [], []
    for q, (dx, dy) in enumerate([(0, 0), (QUADRANT_KM, 0), (0, QUADRANT_KM), (QUADRANT_KM,) * 2]):
        for t in paper["targets"]:
            copy = dict(t, id=q * len(paper["targets"]) + t["id"])
            copy["x_km"], copy["y_km"] = t["x_km"] + dx, t["y_km"] + dy
            targets.append(copy)
        for z in paper["threats"]:
            threats.append(dict(z, x_km=z["x_km"] + dx, y_km=z["y_km"] + dy))
    return targets, threats


def edge_starts(
    count: int, threats: list[dict], clearance_km: float
) -> list[tuple[float, float, float]]:
    """``count`` starts (x, y, heading deg) spread evenly over the rings, heading to the
    centre (rounded to the grid's 45 degrees), at cell centres, clear of every threat."""
    rings = RINGS_KM[: 1 if count <= 150 else 2]
    spots: list[tuple[float, float]] = []
    per_ring = math.ceil(count / len(rings)) + 40  # spare for those a threat takes
    for inset in rings:
        side = SIDE_KM - 2 * inset
        for k in range(per_ring):
            s = 4 * side * k / per_ring  # distance along the ring, from its south-west corner
            edge, along = divmod(s, side)
            x, y = [(inset + along, inset), (SIDE_KM - inset, inset + along),
                    (SIDE_KM - inset - along, SIDE_KM - inset),
                    (inset, SIDE_KM - inset - along)][int(edge)]  # fmt: skip
            x, y = math.floor(x) + 0.5, math.floor(y) + 0.5
            clear = all(
                math.hypot(x - z["x_km"], y - z["y_km"]) > z["radius_km"] + clearance_km
                for z in threats
            )
            if clear and (x, y) not in spots:
                spots.append((x, y))
    if len(spots) < count:
        raise SystemExit(f"only {len(spots)} start spots for {count} UAVs")
    chosen = [spots[round(i * len(spots) / count)] for i in range(count)]
    starts = []
    for x, y in chosen:
        # counter-clockwise from east, as ``planner.grid.heading_of_angle`` reads it
        toward = math.degrees(math.atan2(SIDE_KM / 2 - y, SIDE_KM / 2 - x)) % 360
        starts.append((x, y, round(toward / 45) % 8 * 45.0))
    return starts


def scenario_text(count: int, paper: dict) -> str:
    targets, threats = quadrant_copies(paper)
    clearance = PlannerConfig().detection_radius_km + START_THREAT_GAP_KM
    lines = [
        f'name = "swarm-{count}uav"',
        f'description = "{count} UAVs from the edges of a 200 x 200 km area: four copies of the '
        'paper\'s section 4.3 world (64 targets, 20 threats), L_max = 330 km. Written by '
        'tools/swarm_scenarios.py."',
        "steps = 250",
        "threats_known = false",
        "",
        "[parameters]",
        "grid_nx = 200",
        "grid_ny = 200",
        *(f"{k} = {str(v).lower() if isinstance(v, bool) else v}"
          for k, v in paper["parameters"].items()),
        "",
        "[uavs]",
        f"count = {count}",
        "random_start = false",
    ]  # fmt: skip
    for x, y, heading in edge_starts(count, threats, clearance):
        lines += [
            "",
            "[[uavs.start]]",
            f"x_km = {x:g}",
            f"y_km = {y:g}",
            f"heading_deg = {heading:g}",
        ]
    for t in targets:
        lines += ["", "[[targets]]", *(f"{k} = {_toml(v)}" for k, v in t.items())]
    for z in threats:
        lines += ["", "[[threats]]", *(f"{k} = {_toml(v)}" for k, v in z.items())]
    return "\n".join(lines) + "\n"


def _toml(value: object) -> str:
    return (
        f'"{value}"'
        if isinstance(value, str)
        else f"{value:g}"
        if isinstance(value, float)
        else str(value)
    )


def main() -> None:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else SCENARIOS
    paper = tomllib.loads((SCENARIOS / "paper-20uav.toml").read_text())
    for count in (100, 500):
        path = out / f"swarm-{count}uav.toml"
        path.write_text(scenario_text(count, paper))
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
