"""Why the baselines rank as they do: PSO and ACOAPF variants against the paper's Algorithms 1-2,
on the same seeds, with the per-target account (targets seen, engaged, conversion) and coverage.

python benchmarks/bench_baseline_fidelity.py [--seeds-2uav 10] [--seeds-10uav 5] [--jobs 2]

Variants (docs/experiments.md, "A fair comparison"):

- ``pso``: the PSO baseline as shipped (5-move receding horizon; search fitness = unsearched
  cells + TPM share + a beyond-horizon value);
- ``pso-eq7``: search fitness = eq 7's J_E only (the unsearched cells of the path's footprints),
  no TPM term, no beyond-horizon value;
- ``pso-eq7-h1``: the same over the next position only (eq 7's U_i*, one move);
- ``pso-no-tpm``: the shipped PSO without its TPM term (beyond-horizon value kept);
- ``pso-no-terminal``: the shipped PSO without its beyond-horizon value (TPM term kept);
- ``acoapf``: ACOAPF as shipped (the APF without the TPM forecast; shared confirmation);
- ``acoapf-static``: the earlier ACOAPF, whose confirmation beliefs had no forecast either;
- ``hapf-aco``: the reference.
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

VARIANTS = (
    "hapf-aco", "pso", "pso-eq7", "pso-eq7-h1", "pso-no-tpm", "pso-no-terminal", "acoapf",
    "acoapf-static",
)  # fmt: skip


def planner_factory(variant: str):
    from planner.acoapf import AcoApfPlanner, StaticTargetProbabilityMaps
    from planner.hapf_aco import HapfAcoPlanner
    from planner.pso import PsoPlanner, PsoSettings

    if variant == "hapf-aco":
        return HapfAcoPlanner
    if variant == "acoapf":
        return AcoApfPlanner
    if variant == "acoapf-static":

        class AllStatic(AcoApfPlanner):
            """Sensing and confirmation on the forecast-free map as well (before the fix)."""

            def __init__(self, scenario, starts, seed):
                super().__init__(scenario, starts, seed)
                static = StaticTargetProbabilityMaps(scenario.targets, self.cfg, self.n)
                self.beliefs.tpm = static  # no twin: the field reads it too

        return AllStatic
    settings = {
        "pso": PsoSettings(),
        "pso-eq7": PsoSettings(tpm_weight=0.0, terminal_weight=0.0),
        "pso-eq7-h1": PsoSettings(tpm_weight=0.0, terminal_weight=0.0, horizon_steps=1),
        "pso-no-tpm": PsoSettings(tpm_weight=0.0),
        "pso-no-terminal": PsoSettings(terminal_weight=0.0),
    }[variant]
    return lambda scenario, starts, seed: PsoPlanner(scenario, starts, seed, settings)


def one_run(job: tuple[str, str, int]) -> tuple[str, str, int, dict]:
    from planner.registry import BUILT_IN, register
    from planner.scenario import load_scenario
    from sim_gateway import offline_runner

    name, variant, seed = job
    if variant not in BUILT_IN:
        register(variant, planner_factory(variant))
    result = offline_runner.run_offline(load_scenario(name), seed, None, variant)
    totals = result["target_account"]["totals"]
    return (
        name,
        variant,
        seed,
        {
            "engaged": result["engaged_count"],
            "seen": totals["seen"],
            "confirmed": totals["confirmed"],
            "coverage": result["coverage"],
            "misses": result["engage_misses"],
            "returned": result["returned_count"],
            "violations": sum(result["violations"].values()),
            **{
                f"{stage}:{kind}": counts[stage]
                for kind, counts in result["target_account"]["by_kind"].items()
                for stage in ("seen", "engaged")
            },
        },
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds-2uav", type=int, default=10)
    parser.add_argument("--seeds-10uav", type=int, default=5)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--jobs", type=int, default=2)
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    jobs = [
        (name, variant, seed)
        for name, seeds in (("paper-10uav", args.seeds_10uav), ("paper-2uav", args.seeds_2uav))
        for variant in args.variants.split(",")
        for seed in range(1, seeds + 1)
    ]
    started = time.perf_counter()
    rows: dict[tuple[str, str], list[dict]] = {}
    with ProcessPoolExecutor(args.jobs) as pool:
        for name, variant, _, m in pool.map(one_run, jobs):
            rows.setdefault((name, variant), []).append(m)
    print("| scenario | variant | seeds | seen | confirmed | engaged | conversion | misses/run "
          "| coverage % | returned | violations |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for (name, variant), runs in sorted(rows.items(), key=lambda kv: (kv[0][0], VARIANTS.index(
            kv[0][1]))):  # fmt: skip
        mean = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}
        seen = sum(r["seen"] for r in runs)
        conversion = sum(r["engaged"] for r in runs) / seen if seen else float("nan")
        engaged_std = float(np.std([r["engaged"] for r in runs], ddof=1)) if len(runs) > 1 else 0
        print(f"| {name} | {variant} | {len(runs)} | {mean['seen']:.1f} | {mean['confirmed']:.1f}"
              f" | {mean['engaged']:.1f} ± {engaged_std:.1f} | {conversion:.2f} | "
              f"{mean['misses']:.1f} | {100 * mean['coverage']:.1f} | {mean['returned']:.1f} | "
              f"{int(sum(r['violations'] for r in runs))} |")  # fmt: skip
    kinds = ("known_position", "known_speed", "known_velocity", "unknown_position")
    print("\nEngaged / seen per run, by target kind:\n")
    print(f"| scenario | variant | {' | '.join(kinds)} |")
    print("|---|---|" + "---|" * len(kinds))
    for (name, variant), runs in sorted(rows.items(), key=lambda kv: (kv[0][0], VARIANTS.index(
            kv[0][1]))):  # fmt: skip
        cells = [
            f"{np.mean([r.get(f'engaged:{k}', 0) for r in runs]):.1f} / "
            f"{np.mean([r.get(f'seen:{k}', 0) for r in runs]):.1f}"
            for k in kinds
        ]
        print(f"| {name} | {variant} | {' | '.join(cells)} |")
    print(f"\n{len(jobs)} runs in {time.perf_counter() - started:.0f} s on {args.jobs} processes")


if __name__ == "__main__":
    main()
