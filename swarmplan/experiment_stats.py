"""Tables and statistics of an experiment (the paper's section 4): one CSV row per run, mean and
standard deviation per (scenario, algorithm), the Friedman test across algorithms with the
seeds as blocks (``scipy.stats.friedmanchisquare``), and the Markdown report next to the
paper's numbers.

The CSVs are byte-for-byte reproducible: rows in canonical order (scenario, algorithm in the
paper's order, seed), fixed number formats, ``\\n`` line ends, and no wall times in them.
Standard deviations are sample standard deviations (ddof = 1; 0 for a single run).
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

from swarmplan.experiment_runner import ALGORITHMS, EXPERIMENTS


@dataclass(frozen=True)
class Metric:
    key: str  # column name
    label: str  # for the report
    fmt: str  # CSV format of one run's value


#: Per-run metrics (planner.metrics, eqs 4-5), in CSV column order.
METRICS = (
    Metric("engaged_count", "targets engaged", "{:d}"),
    Metric("engaged_value", "value engaged J_T", "{:.1f}"),
    Metric("coverage", "coverage J_E after the last step", "{:.6f}"),
    Metric("coverage_slope_50", "coverage slope over the first 50 steps (per step)", "{:.8f}"),
    Metric("returned_count", "UAVs back at their start", "{:d}"),
    Metric("min_separation_km", "minimum separation (km)", "{:.4f}"),
)
VIOLATIONS = ("threat", "separation", "turn", "range")
#: The metrics compared across algorithms by the Friedman test (the paper's Figs. 6-7, 11-12).
TESTED = ("engaged_count", "coverage", "coverage_slope_50")

#: The paper's numbers (section 4.2 text and section 4.3 text), by (scenario, algorithm).
PAPER = {
    ("paper-2uav", "pso"): {"engaged_count": 2.5},
    ("paper-2uav", "acoapf"): {"engaged_count": 4.5},
    ("paper-2uav", "hapf-aco"): {"engaged_count": 5.5},
    ("paper-10uav", "hapf-aco"): {
        "engaged_count": 12.5,
        "coverage_shown": 0.845,
        "engaged_shown": 14,
        "returned_shown": 7,
    },
    ("paper-20uav", "hapf-aco"): {
        "engaged_count": 15.7,
        "coverage_shown": 0.931,
        "engaged_shown": 16,
    },
}


def scenario_order(experiment: str) -> dict[str, int]:
    return {name: i for i, name in enumerate(EXPERIMENTS[experiment].scenarios)}


def algorithm_rank(name: str) -> tuple[int, str]:
    return (ALGORITHMS.index(name), name) if name in ALGORITHMS else (len(ALGORITHMS), name)


def sorted_results(results: Sequence[dict]) -> list[dict]:
    """Canonical order: scenario (the experiment's order), algorithm (the paper's), seed."""

    def key(r: dict) -> tuple:
        order = scenario_order(r["experiment"]) if r.get("experiment") in EXPERIMENTS else {}
        return (
            order.get(r["scenario"], len(order)),
            r["scenario"],
            algorithm_rank(r["algorithm"]),
            r["seed"],
        )

    return sorted(results, key=key)


def _format(value, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    return fmt.format(value)


def _csv_text(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue()


def runs_csv(results: Sequence[dict]) -> str:
    """One row per run: identity, the metrics and the violation counts of eq 5's constraints."""
    header = [
        "experiment",
        "scenario",
        "uav_count",
        "algorithm",
        "seed",
        "steps",
        *(m.key for m in METRICS),
        *(f"violations_{v}" for v in VIOLATIONS),
    ]
    rows = []
    for r in sorted_results(results):
        rows.append(
            [
                r.get("experiment", ""),
                r["scenario"],
                str(r["uav_count"]),
                r["algorithm"],
                str(r["seed"]),
                str(r["steps"]),
                *(_format(r[m.key], m.fmt) for m in METRICS),
                *(str(r["violations"][v]) for v in VIOLATIONS),
            ]
        )
    return _csv_text(header, rows)


def mean_std(values: Sequence[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof = 1; 0 for one value); NaN when empty."""
    a = np.asarray([v for v in values if v is not None], dtype=float)
    if a.size == 0:
        return math.nan, math.nan
    return float(a.mean()), float(a.std(ddof=1)) if a.size > 1 else 0.0


def groups(results: Sequence[dict]) -> dict[tuple[str, str], list[dict]]:
    """Runs by (scenario, algorithm), in canonical order, each group sorted by seed."""
    out: dict[tuple[str, str], list[dict]] = {}
    for r in sorted_results(results):
        out.setdefault((r["scenario"], r["algorithm"]), []).append(r)
    return out


def summary_rows(results: Sequence[dict]) -> list[dict]:
    """Per (scenario, algorithm): runs, mean and std of every metric, violation totals."""
    rows = []
    for (scenario, algorithm), runs in groups(results).items():
        row: dict = {
            "scenario": scenario,
            "uav_count": runs[0]["uav_count"],
            "algorithm": algorithm,
            "runs": len(runs),
        }
        for m in METRICS:
            row[f"{m.key}_mean"], row[f"{m.key}_std"] = mean_std([r[m.key] for r in runs])
        seps = [r["min_separation_km"] for r in runs if r["min_separation_km"] is not None]
        row["min_separation_km_min"] = min(seps) if seps else math.nan
        for v in VIOLATIONS:
            row[f"violations_{v}"] = sum(r["violations"][v] for r in runs)
        rows.append(row)
    return rows


def summary_csv(results: Sequence[dict]) -> str:
    rows = summary_rows(results)
    header = ["scenario", "uav_count", "algorithm", "runs"]
    for m in METRICS:
        header += [f"{m.key}_mean", f"{m.key}_std"]
    header += ["min_separation_km_min", *(f"violations_{v}" for v in VIOLATIONS)]
    body = []
    for row in rows:
        cells = [row["scenario"], str(row["uav_count"]), row["algorithm"], str(row["runs"])]
        for m in METRICS:
            cells += [
                _format(row[f"{m.key}_mean"], "{:.6f}"),
                _format(row[f"{m.key}_std"], "{:.6f}"),
            ]
        cells += [
            _format(row["min_separation_km_min"], "{:.4f}"),
            *(str(row[f"violations_{v}"]) for v in VIOLATIONS),
        ]
        body.append(cells)
    return _csv_text(header, body)


def friedman_rows(results: Sequence[dict]) -> list[dict]:
    """Friedman test across the algorithms of each scenario, seeds as blocks (only the seeds
    every algorithm ran). Needs at least 3 algorithms; NaN where the test is undefined (fewer
    than 3 algorithms or 2 seeds, or every value tied)."""
    rows = []
    by_scenario: dict[str, dict[str, dict[int, dict]]] = {}
    for (scenario, algorithm), runs in groups(results).items():
        by_scenario.setdefault(scenario, {})[algorithm] = {r["seed"]: r for r in runs}
    for scenario, per_algorithm in by_scenario.items():
        algorithms = list(per_algorithm)
        seeds = sorted(set.intersection(*(set(v) for v in per_algorithm.values())))
        for metric in TESTED:
            samples = [[per_algorithm[a][s][metric] for s in seeds] for a in algorithms]
            statistic, p = math.nan, math.nan
            if len(algorithms) >= 3 and len(seeds) >= 2:
                with np.errstate(all="ignore"):
                    result = stats.friedmanchisquare(*samples)
                statistic, p = float(result.statistic), float(result.pvalue)
            rows.append(
                {
                    "scenario": scenario,
                    "metric": metric,
                    "algorithms": " ".join(algorithms),
                    "blocks": len(seeds),
                    "statistic": statistic,
                    "p_value": p,
                }
            )
    return rows


def friedman_csv(results: Sequence[dict]) -> str:
    header = ["scenario", "metric", "algorithms", "blocks", "chi2", "p_value"]
    body = [
        [
            r["scenario"],
            r["metric"],
            r["algorithms"],
            str(r["blocks"]),
            _format(r["statistic"], "{:.6f}"),
            _format(r["p_value"], "{:.6e}"),
        ]
        for r in friedman_rows(results)
    ]
    return _csv_text(header, body)


# ----------------------------------------------------------------------------- the report


def _cpu_line(results: Sequence[dict]) -> list[str]:
    """The runs' own CPU time: what the work costs, whatever else loaded the machine."""
    cpu = [r["cpu_time_s"] for r in results if r.get("cpu_time_s") is not None]
    if len(cpu) != len(results) or not cpu:
        return []
    total = sum(cpu)
    cores = os.cpu_count() or 1
    return [
        f"- CPU time of the runs: {total:.1f} s in all (about {total / cores:.0f} s of wall time "
        f"on this machine's {cores} cores, otherwise idle)"
    ]


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _pm(mean: float, std: float, scale: float = 1.0, digits: int = 2) -> str:
    if math.isnan(mean):
        return "n/a"
    return f"{mean * scale:.{digits}f} ± {std * scale:.{digits}f}"


RESULT_COLUMNS = (
    "scenario", "algorithm", "runs", "engaged (paper)", "engaged", "value J_T", "coverage %",
    "slope first 50 (%/step)", "returned", "min sep. km (min)", "violations t/s/m/r",
)  # fmt: skip


def results_table(results: Sequence[dict]) -> str:
    """The main Markdown table: mean ± std per (scenario, algorithm) next to the paper."""
    lines = ["| " + " | ".join(RESULT_COLUMNS) + " |", "|" + "---|" * len(RESULT_COLUMNS)]
    for row in summary_rows(results):
        paper = PAPER.get((row["scenario"], row["algorithm"]), {}).get("engaged_count")
        sep = _pm(row["min_separation_km_mean"], row["min_separation_km_std"])
        cells = [
            row["scenario"],
            row["algorithm"],
            str(row["runs"]),
            "—" if paper is None else str(paper),
            _pm(row["engaged_count_mean"], row["engaged_count_std"]),
            _pm(row["engaged_value_mean"], row["engaged_value_std"], digits=1),
            _pm(row["coverage_mean"], row["coverage_std"], 100, 1),
            _pm(row["coverage_slope_50_mean"], row["coverage_slope_50_std"], 100, 3),
            _pm(row["returned_count_mean"], row["returned_count_std"], digits=1)
            + f" / {row['uav_count']}",
            f"{sep} ({row['min_separation_km_min']:.2f})",
            "/".join(str(row[f"violations_{v}"]) for v in VIOLATIONS),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def friedman_table(results: Sequence[dict]) -> str:
    lines = [
        "| scenario | metric | algorithms | seeds (blocks) | chi² | p |",
        "|---|---|---|---|---|---|",
    ]
    for r in friedman_rows(results):
        chi2 = "n/a" if math.isnan(r["statistic"]) else f"{r['statistic']:.2f}"
        p = "n/a" if math.isnan(r["p_value"]) else f"{r['p_value']:.3g}"
        cells = [r["scenario"], r["metric"], r["algorithms"], str(r["blocks"]), chi2, p]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


CONVERSION_COLUMNS = (
    "scenario", "algorithm", "seeds", "targets seen (>= 3 steps)", "confirmed", "engaged",
    "conversion", "misses per run", "paper's engaged",
)  # fmt: skip


def conversion_rows(results: Sequence[dict]) -> list[dict]:
    """Per (scenario, algorithm), from each run's ``target_account``: mean targets seen (in a
    footprint for >= 3 steps), confirmed and engaged per run, and the conversion engaged / seen
    (of the sums over the runs, so the ratio of the means)."""
    rows = []
    for (scenario, algorithm), runs in groups(results).items():
        runs = [r for r in runs if r.get("target_account")]
        if not runs:
            continue
        totals = [r["target_account"]["totals"] for r in runs]
        seen = sum(t["seen"] for t in totals)
        engaged = sum(t["engaged"] for t in totals)
        confirmed = [t["confirmed"] for t in totals if t["confirmed"] is not None]
        seeds = sorted(r["seed"] for r in runs)
        rows.append({
            "scenario": scenario,
            "algorithm": algorithm,
            "runs": len(runs),
            "seeds": f"{seeds[0]}-{seeds[-1]}" if len(seeds) > 1 else str(seeds[0]),
            "seen": seen / len(runs),
            "confirmed": sum(confirmed) / len(confirmed) if confirmed else math.nan,
            "engaged": engaged / len(runs),
            "conversion": engaged / seen if seen else math.nan,
            "misses": sum(r["engage_misses"] for r in runs) / len(runs),
            "paper": PAPER.get((scenario, algorithm), {}).get("engaged_count"),
        })  # fmt: skip
    return rows


def conversion_table(results: Sequence[dict]) -> str:
    """The issue-13 table (Markdown): scenario, seeds, seen, confirmed, engaged, conversion."""
    lines = ["| " + " | ".join(CONVERSION_COLUMNS) + " |", "|" + "---|" * len(CONVERSION_COLUMNS)]
    for row in conversion_rows(results):
        cells = [
            row["scenario"], row["algorithm"], row["seeds"], f"{row['seen']:.1f}",
            "n/a" if math.isnan(row["confirmed"]) else f"{row['confirmed']:.1f}",
            f"{row['engaged']:.1f}",
            "n/a" if math.isnan(row["conversion"]) else f"{row['conversion']:.2f}",
            f"{row['misses']:.1f}", "—" if row["paper"] is None else str(row["paper"]),
        ]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


PAPER_TEXT = {
    "efficiency": (
        'Section 4.2 (30 runs, 250 iterations): mean engaged ("destroyed") targets PSO 2.5, '
        "ACOAPF 4.5, HAPF-ACO 5.5; the differences are significant by Friedman's test "
        "(p < 0.05). Coverage and the slope over the first 50 iterations are shown only as "
        "plots (Fig. 6)."
    ),
    "swarm": (
        "Section 4.3 (HAPF-ACO only): the run shown reaches 84.5% coverage with 14 targets "
        "engaged and 7 of 10 UAVs back at their start (10 UAVs), 93.1% and 16 engaged "
        "(20 UAVs); over 30 runs the mean engaged is 12.5 (10 UAVs) and 15.7 (20 UAVs); the "
        "minimum separation never falls below d_min = 1 km (Fig. 13). The paper flies no PSO "
        "or ACOAPF in this experiment."
    ),
}


def report_markdown(
    experiment: str,
    results: Sequence[dict],
    *,
    command: str,
    wall_time_s: float,
    where: str,
    load_before: tuple[float, ...],
    load_after: tuple[float, ...],
    figures: Sequence[str],
) -> str:
    spec = EXPERIMENTS[experiment]
    steps = sorted({r["steps"] for r in results})
    seeds = sorted({r["seed"] for r in results})
    seed_text = f"{seeds[0]}-{seeds[-1]}" if seeds else "none"
    n_algorithms = _count(len({r["algorithm"] for r in results}), "algorithm")
    n_scenarios = _count(len({r["scenario"] for r in results}), "scenario")
    load = lambda t: " / ".join(f"{x:.2f}" for x in t)  # noqa: E731
    lines = [
        f"# Experiment `{experiment}` (paper section {spec.section})",
        "",
        f"{spec.description}.",
        "",
        f"- command: `{command}`",
        f"- runs: {len(results)} ({n_algorithms} x {n_scenarios} x "
        f"{_count(len(seeds), 'seed')} {seed_text}), {', '.join(map(str, steps))} steps each",
        f"- wall time: {wall_time_s:.1f} s on {where}",
        *_cpu_line(results),
        f"- load average (1/5/15 min) before: {load(load_before)}, after: {load(load_after)}",
        "",
        "## Results (mean ± standard deviation over the seeds)",
        "",
        results_table(results),
        "",
        "Violations are totals over all runs of C_t (threat) / C_c (separation) / C_m (turn) / "
        "C_r (range); `returned` counts UAVs that ended within one cell of their start. ACOAPF "
        "ignores the range constraint when planning: a UAV of it that reaches L_max stops (it "
        "is lost, not returned) instead of flying on (docs/experiments.md).",
        "",
        "## Targets: seen, confirmed, engaged (ground truth, mean per run)",
        "",
        conversion_table(results),
        "",
        "A target counts as seen when it was inside some UAV's 3 km footprint at >= 3 decision "
        "steps; conversion is engaged / seen; the funnel figure splits the stages by target "
        "kind (`target_account` of each run, docs/experiments.md).",
        "",
        *(f"![Target funnel by kind]({f})\n" for f in figures if f.endswith("targets_funnel.png")),
        "## Friedman test across algorithms (seeds as blocks)",
        "",
        friedman_table(results),
        "",
        "## The paper",
        "",
        PAPER_TEXT[experiment],
        "",
        "## Files",
        "",
        "- `runs.csv`: one row per run; `summary.csv`: mean and std per scenario and algorithm; "
        "`friedman.csv`: the tests; `runs/SCENARIO/ALGORITHM/seed-NNNN.json`: each run's full "
        "result.",
        *(f"- `{f}`" for f in figures),
        "",
    ]
    return "\n".join(lines)
