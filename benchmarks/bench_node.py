"""The cost of one UAV's own planner (``planner.uav_node.UavNode``), as a companion computer
would carry it: time per decision step and memory, on the paper's 100 x 100 cell area and a
200 x 200 one.

python benchmarks/bench_node.py [--scenario paper-20uav] [--sizes 100 200] [--steps 40]

The swarm flies offline (``sim_gateway.offline_runner``) as nodes on a perfect in-process link
(``planner.swarm_bus``); each node's five calls of a step (begin, hear, rank, claim, finish) are
timed in CPU time of the process (``time.process_time``: a shared machine's load stretches wall
time, not this), so the link and the offline world are left out. Memory: what building one node
allocates (its beliefs: TPM layers, pheromone, coverage; ``tracemalloc``), and the most
allocated at once while one node steps. The batched planner's time per UAV per step over the
same run is printed beside it.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
import tracemalloc

from planner.registry import register
from planner.scenario import Scenario, load_scenario
from planner.swarm_bus import LinkModel, NodeSwarmPlanner
from planner.uav_node import UavNode
from sim_gateway.offline_runner import run_offline

PHASES = ("begin", "hear", "rank", "claim", "finish")


def timed_nodes() -> dict[tuple[int, int], dict[str, float]]:
    """Wrap ``UavNode``'s phases with timers: seconds by (uav, step) and phase."""
    spent: dict[tuple[int, int], dict[str, float]] = {}
    for phase in PHASES:
        original = getattr(UavNode, phase)

        def timed(self, *args, _original=original, _phase=phase, **kwargs):
            started = time.process_time()
            out = _original(self, *args, **kwargs)
            key = (self.uav, self.beliefs.k if _phase != "finish" else self.beliefs.k - 1)
            row = spent.setdefault(key, dict.fromkeys(PHASES, 0.0))
            row[_phase] += time.process_time() - started
            return out

        setattr(UavNode, phase, timed)
    return spent


def node_memory(scenario: Scenario, seed: int, steps: int) -> tuple[float, float]:
    """(MB allocated by building one node, MB most allocated at once over ``steps`` steps of
    the swarm, per node): ``tracemalloc`` over a swarm of nodes, divided by its size."""
    tracemalloc.start()
    planner = NodeSwarmPlanner(scenario, scenario.starts_for_seed(seed), seed)
    built = tracemalloc.get_traced_memory()[0] / len(planner.nodes)
    tracemalloc.reset_peak()
    register("nodes-bench-memory", lambda sc, st, s: planner)
    run_offline(scenario, seed, steps, "nodes-bench-memory", account=False)
    peak = tracemalloc.get_traced_memory()[1] / len(planner.nodes)
    tracemalloc.stop()
    return built / 1e6, peak / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="paper-20uav")
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 200])
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    spent = timed_nodes()
    register("nodes-bench", lambda sc, st, s: NodeSwarmPlanner(sc, st, s, LinkModel()))
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    print(f"{args.scenario}, seed {args.seed}, {args.steps} steps, CPU time; load average {load}")
    print("| cells | UAVs | node step: median | p95 | per phase (ms): " + " / ".join(PHASES)
          + " | batched, per UAV step | node memory: built | peak while stepping |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for size in args.sizes:
        scenario = load_scenario(args.scenario).with_config(grid_nx=size, grid_ny=size)
        n = len(scenario.starts_for_seed(args.seed))
        started = time.process_time()
        run_offline(scenario, args.seed, args.steps, "hapf-aco", account=False)
        batched = (time.process_time() - started) / (args.steps * n)
        spent.clear()
        run_offline(scenario, args.seed, args.steps, "nodes-bench", account=False)
        totals = [sum(row.values()) for row in spent.values()]
        phases = [statistics.mean(row[p] for row in spent.values()) * 1e3 for p in PHASES]
        built, peak = node_memory(scenario, args.seed, min(args.steps, 10))
        p95 = statistics.quantiles(totals, n=20)[-1]
        print(f"| {size} x {size} | {n} | {statistics.median(totals) * 1e3:.1f} ms | "
              f"{p95 * 1e3:.1f} ms | {' / '.join(f'{p:.2f}' for p in phases)} | "
              f"{batched * 1e3:.2f} ms | {built:.1f} MB | {peak:.1f} MB |")  # fmt: skip


if __name__ == "__main__":
    main()
