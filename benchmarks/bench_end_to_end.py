"""End-to-end benchmark: the full paper 10-UAV scenario flown over loopback UDP MAVLink
(`swarmplan demo`: simulator subprocess + daemon, lockstep by default) next to the offline runs
of the same seeds: the paper's (`swarmplan run`: grid UAVs that fly cell centres) and the one
planned as the daemon plans it (`swarmplan run --as-flown`: the margins a flown plane needs,
mavlink_bridge/mission/flown_planning.py).

    python benchmarks/bench_end_to_end.py [--seeds 1 .. 10] [--speedup X] [--steps 250]
                                          [--no-leg-timing]

Prints, per seed, wall time, coverage, engaged count/value, returned, minimum separation and the
violations measured from telemetry (threat, separation, turn, range), plus the simulator's own
count of fence (threat circle) breaches along the whole flown path; then whether every MAVLink
run took under 60 s, had zero violations, and had coverage / engaged value within the spread
(min..max) of the offline runs of the same seeds; and, since one MAVLink run of a seed is not
the offline run of that seed (telemetry noise and real turns change every later decision), the
paired comparison over the seeds: mean difference and a Wilcoxon signed-rank p-value (no
systematic difference when p is large). Both against the as-flown offline runs (the agreement
check: what the MAVLink loop itself changes) and against the paper's (what flying real planes
costs besides). Last, the UAV-steps the planner spent in each decision mode, offline and flown.
``--speedup X`` flies paced instead of lockstep;
``--no-leg-timing`` flies every leg at the scenario's speed (docs/daemon.md, "Leg timing").
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from scipy.stats import wilcoxon

REPO = Path(__file__).resolve().parents[1]


def swarmplan_json(args: list[str]) -> dict:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run(
        [sys.executable, "-m", "swarmplan", *args, "--json"],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO,
        timeout=900,
    )
    if proc.returncode != 0:
        raise SystemExit(
            f"swarmplan {' '.join(args)} failed: {proc.stderr.strip().splitlines()[-1:]}"
        )
    return json.loads(proc.stdout)


def fence_breaches(out: Path) -> str:
    """The simulator's count of threat-circle entries (its summary, the last line of sim.log)."""
    try:
        last = (out / "sim.log").read_text().strip().splitlines()[-1]
        return str(json.loads(last).get("fence_breaches", "?"))
    except (OSError, IndexError, ValueError):
        return "?"


def row(kind: str, seed: int, r: dict, breaches: str = "-") -> str:
    v = r["violations"]
    sep = r["min_separation_km"]
    return (
        f"{kind:<8} {seed:>4} {r['wall_time_s']:>8.1f} {100 * r['coverage']:>8.1f} "
        f"{r['engaged_count']:>7} "
        f"{r['engaged_value']:>6g} {r['returned_count']:>8} "
        f"{'-' if sep is None else f'{sep:.2f}':>7} "
        f"{v['threat']:>6} {v['separation']:>4} {v['turn']:>4} {v['range']:>5} {breaches:>6}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="paper-10uav")
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 11)))
    parser.add_argument("--speedup", type=float, default=None, help="paced, not lockstep")
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--no-leg-timing", action="store_true")
    args = parser.parse_args()
    steps = ["--steps", str(args.steps)] if args.steps else []
    print(
        f"{'run':<8} {'seed':>4} {'wall s':>8} {'cover %':>8} {'engaged':>7} {'value':>6} "
        f"{'returned':>8} "
        f"{'min sep':>7} {'threat':>6} {'sep':>4} {'turn':>4} {'range':>5} {'fence':>6}"
    )
    pace = [] if args.speedup is None else ["--speedup", f"{args.speedup:g}"]
    pace += ["--no-leg-timing"] if args.no_leg_timing else []
    offline_runs, flown_plan_runs, mavlink_runs = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            offline = swarmplan_json(
                ["run", args.scenario, "--seed", str(seed), *steps, "--out", f"{tmp}/off{seed}"]
            )
            print(row("offline", seed, offline), flush=True)
            offline_runs.append(offline)
            as_flown = swarmplan_json(
                ["run", args.scenario, "--as-flown", "--seed", str(seed), *steps,
                 "--out", f"{tmp}/asf{seed}"]
            )  # fmt: skip
            print(row("as-flown", seed, as_flown), flush=True)
            flown_plan_runs.append(as_flown)
            e2e = swarmplan_json(
                [
                    "demo",
                    args.scenario,
                    "--seed",
                    str(seed),
                    *steps,
                    *pace,
                    "--out",
                    f"{tmp}/e2e{seed}",
                ]
            )
            print(row("mavlink", seed, e2e, fence_breaches(Path(tmp) / f"e2e{seed}")), flush=True)
            mavlink_runs.append(e2e)
            print(
                f"{'':<13} overrides {e2e.get('envelope_overrides')} lost {e2e.get('lost_uavs')} "
                f"refused {e2e.get('refused_commands')}",
                flush=True,
            )

    if mavlink_runs:
        print()
        print(f"planned with, offline --as-flown: {flown_plan_runs[0]['planned_with']}")
        print(f"planned with, mavlink:            {mavlink_runs[0]['planned_with']}")
        worst_wall = max(r["wall_time_s"] for r in mavlink_runs)
        violations = sum(sum(r["violations"].values()) for r in mavlink_runs)
        print(f"mavlink wall time: max {worst_wall:.1f} s (target < 60 s)")
        print(f"mavlink violations, all seeds: {violations} (target 0)")
        for label, runs in (("offline --as-flown", flown_plan_runs), ("offline", offline_runs)):
            print(f"\nmavlink against {label}:")
            for line in verdict(runs, mavlink_runs):
                print(line)
            print(modes_line(runs, mavlink_runs))


def verdict(offline: list[dict], mavlink: list[dict]) -> list[str]:
    """Coverage, engaged value and count of the MAVLink runs against offline runs of the same
    seeds: how many lie within the offline spread, and the paired difference."""
    lines = []
    for key, scale, unit in (
        ("coverage", 100, "%"),
        ("engaged_value", 1, ""),
        ("engaged_count", 1, ""),
        ("returned_count", 1, ""),
    ):
        lo = min(r[key] for r in offline) * scale
        hi = max(r[key] for r in offline) * scale
        got = [r[key] * scale for r in mavlink]
        inside = sum(lo <= g <= hi for g in got)
        mean_off = sum(r[key] for r in offline) * scale / len(offline)
        mean_mav = sum(got) / len(got)
        diff = [g - r[key] * scale for g, r in zip(got, offline, strict=True)]
        p = wilcoxon(diff).pvalue if any(diff) else 1.0
        lines.append(
            f"{key:<14} offline {lo:.1f}..{hi:.1f}{unit} (mean {mean_off:.1f}), mavlink mean "
            f"{mean_mav:.1f}{unit}; {inside}/{len(got)} mavlink runs inside the offline spread; "
            f"paired difference {sum(diff) / len(diff):+.2f}{unit}, Wilcoxon p = {p:.3f}"
        )
    return lines


def modes_line(offline: list[dict], mavlink: list[dict]) -> str:
    """The planner's UAV-steps a run in each decision mode, offline -> MAVLink (means): how the
    flown runs' conduct differs (e.g. more of the return mode, docs/results.md)."""

    def mean(runs: list[dict], mode: str) -> float:
        return sum(r["decision_modes"][mode] for r in runs) / len(runs)

    modes = offline[0]["decision_modes"]
    parts = [f"{m} {mean(offline, m):.0f} -> {mean(mavlink, m):.0f}" for m in modes]
    return "UAV-steps a run by planner mode, offline -> mavlink: " + ", ".join(parts)


if __name__ == "__main__":
    main()
