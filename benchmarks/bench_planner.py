"""Wall time of one 250-step offline run of each paper scenario, and per planning step per UAV.

python benchmarks/bench_planner.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import time

from planner.scenario import load_scenario
from sim_gateway.offline_runner import run_offline


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    print(
        f"{'scenario':<12} {'UAVs':>4} {'run (s)':>9} {'per step (ms)':>14}"
        f" {'per step per UAV (ms)':>22}"
    )
    baseline = None
    for name in ("paper-2uav", "paper-10uav", "paper-20uav"):
        scenario = load_scenario(name)
        best = float("inf")
        for _ in range(args.repeat):
            started = time.perf_counter()
            run_offline(scenario, args.seed, 250)
            best = min(best, time.perf_counter() - started)
        n = scenario.uav_count
        per_step = best / 250 * 1000
        baseline = baseline or per_step / n
        print(f"{name:<12} {n:>4} {best:>9.2f} {per_step:>14.2f} {per_step / n:>22.3f}"
              f"   ({per_step / n / baseline:.2f}x the 2-UAV cost per UAV)")  # fmt: skip


if __name__ == "__main__":
    main()
