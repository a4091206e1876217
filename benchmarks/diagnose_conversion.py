"""Why seen targets are not engaged: each target seen (inside some UAV's 3 km footprint at >= 3
decision steps) but not engaged, classified from the per-target account (ground truth, after
the run; the planner never sees it) by the furthest stage of section 3.2.1 it reached:

- ``no suspicion``: the swarm's belief that a target lay within the engage radius of where it
  really was never reached ``pursue_threshold`` (split by the looks that reported it, b = 1 at
  its cell, and by its closest approach to a UAV: beyond d_in the sensor is weak, eq 17);
- ``suspected, not pursued``: the belief reached ``pursue_threshold`` but no UAV went for it;
- ``pursued, not confirmed``: a UAV went for it, the belief never reached ``confirm_threshold``;
- ``confirmed, not engaged``: confirmed, never engaged (the turn limit, a hand-off, the end).

Engage misses (requests with no target within the engage radius) are counted per run.

Then the conversion of every seen target by two things the planner does not choose alone: how
close some UAV came to it (beyond d_in the sensor is weak, eq 17; a target never within the
engage radius of a UAV cannot have been engaged) and when it was first seen (a target first
seen late meets UAVs that must head home, ``home_by_end``).

nice -n 10 python benchmarks/diagnose_conversion.py --scenario paper-10uav --seeds 1 2 3
nice -n 10 python benchmarks/diagnose_conversion.py --scenario paper-2uav --seeds 1 2 3 4 5 6 \
    --set pursue_threshold=0.05
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections import Counter

import numpy as np

from planner.scenario import load_scenario
from sim_gateway.offline_runner import OfflineStep, run_offline

CLASSES = (
    "no suspicion",
    "suspected, not pursued",
    "pursued, not confirmed",
    "confirmed, not engaged",
)


def closest_approach(steps: list[OfflineStep]) -> dict[int, float]:
    """Per target id, the least distance (km) to any UAV over the steps it was alive."""
    best: dict[int, float] = {}
    for s in steps:
        alive = s.truth[:, 3] > 0
        d = np.hypot(*(s.truth[:, None, 1:3] - s.positions_km[None, :, :]).transpose(2, 0, 1))
        near = d.min(axis=1)
        for tid, dist, a in zip(s.truth[:, 0].astype(int), near, alive, strict=True):
            if a:
                best[tid] = min(best.get(tid, np.inf), float(dist))
    return best


#: Bands of the closest approach (km) and of the first sighting (decision steps).
APPROACH_BANDS_KM = (0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
SIGHTING_BANDS = (0, 50, 100, 150, 200)


def band_table(
    label: str, values: np.ndarray, engaged: np.ndarray, edges: tuple, runs: int, unit: str
) -> list[str]:
    """Lines of a table: per band of ``values`` (the last band open above), seen targets per
    run, engaged per run and the conversion."""
    lines = [f"{label}:"]
    bounds = list(edges) + [np.inf]
    for low, high in zip(bounds[:-1], bounds[1:], strict=True):
        inside = (values >= low) & (values < high)
        span = f"{low:g}-{high:g} {unit}" if np.isfinite(high) else f">= {low:g} {unit}"
        conversion = f"{engaged[inside].mean():.2f}" if inside.any() else "-"
        lines.append(
            f"  {span:14s} seen {inside.sum() / runs:5.2f} per run, engaged"
            f" {engaged[inside].sum() / runs:5.2f}, conversion {conversion}"
        )
    return lines


def classify(row: dict, cfg) -> str:
    if row["confirmed_step"] is not None:
        return CLASSES[3]
    if row["pursued_step"] is not None:
        return CLASSES[2]
    if row["belief_peak"] >= cfg.pursue_threshold:
        return CLASSES[1]
    return CLASSES[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="paper-10uav")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--set", nargs="*", default=[], help="planner parameters name=value")
    parser.add_argument("--verbose", action="store_true", help="one line per missed target")
    args = parser.parse_args()
    scenario = load_scenario(args.scenario)
    changes = {}
    for item in args.set:
        name, value = item.split("=")
        current = getattr(scenario.config, name)
        changes[name] = type(current)(value) if not isinstance(current, bool) else value == "true"
    if changes:
        scenario = dataclasses.replace(scenario, config=scenario.config.replace(**changes))
    cfg = scenario.config
    counts: Counter = Counter()
    detail: Counter = Counter()
    seen = engaged = misses = 0
    coverage = []
    home = []
    violations = 0
    approach, sighting, converted = [], [], []
    started = time.perf_counter()
    for seed in args.seeds:
        steps: list[OfflineStep] = []
        result = run_offline(scenario, seed, args.steps, observer=steps.append)
        account = result["target_account"]
        near = closest_approach(steps)
        seen += account["totals"]["seen"]
        engaged += account["totals"]["engaged"]
        misses += result["engage_misses"]
        coverage.append(result["coverage"])
        home.append(result["returned_count"])
        violations += sum(result["violations"].values())
        for row in account["targets"]:
            if row["seen"]:
                approach.append(near[row["id"]])
                sighting.append(row["first_sighting"])
                converted.append(row["outcome"] == "engaged")
            if not row["seen"] or row["outcome"] == "engaged":
                continue
            kind = classify(row, cfg)
            counts[kind] += 1
            if kind == CLASSES[0]:
                looks = min(row["detections"], 3)
                band = "<= d_in" if near[row["id"]] <= cfg.sensor_d_in_km else "> d_in"
                detail[(f"{looks}{'+' if looks == 3 else ''} detections", band)] += 1
            if args.verbose:
                print(
                    f"seed {seed} target {row['id']:2d} {row['kind']:16s} {kind:24s}"
                    f" first seen {row['first_sighting']:3d}"
                    f" in fp {row['steps_in_footprint']:3d} det {row['detections']:3d}"
                    f" closest {near[row['id']]:.1f} km peak {row['belief_peak']:.3f}"
                    f" pursued {row['pursued_step']} confirmed {row['confirmed_step']}"
                )
    runs = len(args.seeds)
    print(f"{args.scenario}, seeds {args.seeds}, {changes or 'defaults'}")
    print(
        f"per run: seen {seen / runs:.2f}, engaged {engaged / runs:.2f}, conversion"
        f" {engaged / max(seen, 1):.2f}, engage misses {misses / runs:.2f}, coverage"
        f" {100 * np.mean(coverage):.1f} %, home at the end {np.mean(home):.1f}"
        f" of {scenario.uav_count}, violations {violations}"
    )
    print(f"seen, not engaged: {sum(counts.values())} in {runs} runs")
    for kind in CLASSES:
        print(f"  {kind:24s} {counts[kind]:3d}  ({counts[kind] / runs:.2f} per run)")
    for (looks, band), c in sorted(detail.items()):
        print(f"    no suspicion, {looks:14s} closest {band}: {c}")
    converted_arr = np.array(converted, dtype=bool)
    for line in band_table(
        "seen targets by the closest approach of any UAV", np.array(approach), converted_arr,
        APPROACH_BANDS_KM, runs, "km",
    ) + band_table(
        "seen targets by their first sighting", np.array(sighting), converted_arr,
        SIGHTING_BANDS, runs, "steps",
    ):  # fmt: skip
        print(line)
    print(f"{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
