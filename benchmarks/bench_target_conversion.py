"""The issue-13 table from ground truth: per scenario and algorithm, the mean targets seen (inside
some UAV's 3 km footprint at >= 3 decision steps), confirmed and engaged per run, and the
conversion engaged / seen (``target_account`` of each offline run).

python benchmarks/bench_target_conversion.py                        # the issue's seeds: 1-10 / 1-5 / 1-3
python benchmarks/bench_target_conversion.py --seeds 30 --jobs 2    # 30 seeds of every scenario
python benchmarks/bench_target_conversion.py --scenarios paper-2uav --algorithms hapf-aco
"""  # noqa: E501

from __future__ import annotations

import argparse
import time

from planner.scenario import load_scenario
from swarmplan.experiment_runner import ALGORITHMS, RunTask, execute
from swarmplan.experiment_stats import conversion_table

#: The seeds of the issue's table, per scenario.
ISSUE_SEEDS = {"paper-2uav": 10, "paper-10uav": 5, "paper-20uav": 3}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", default=",".join(ISSUE_SEEDS))
    parser.add_argument("--algorithms", default=",".join(ALGORITHMS))
    parser.add_argument("--seeds", type=int, default=None, help="seeds 1..S (default: the issue's)")
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    tasks = []
    for name in args.scenarios.split(","):
        scenario = load_scenario(name)
        for algorithm in args.algorithms.split(","):
            for seed in range(1, (args.seeds or ISSUE_SEEDS.get(name, 5)) + 1):
                steps = args.steps or scenario.steps
                tasks.append(RunTask("conversion", scenario, algorithm, seed, steps))
    started = time.perf_counter()
    results = list(execute(tasks, args.jobs, progress=True).values())
    print(conversion_table(results))
    print(f"\n{len(tasks)} runs in {time.perf_counter() - started:.1f} s on {args.jobs} processes")


if __name__ == "__main__":
    main()
