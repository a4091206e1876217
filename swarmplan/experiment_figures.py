"""The figures of the paper's section 4, from an experiment's results (matplotlib, no display).

=========================== ================= =================
figure                      efficiency (4.2)  swarm (4.3)
=========================== ================= =================
paths of one run            Fig. 3            Fig. 8
coverage over the steps     Fig. 4            Fig. 9
engaged over the steps      Fig. 5            Fig. 10
coverage metrics (box)      Fig. 6            Fig. 11
engaged per run (box)       Fig. 7            Fig. 12
separation over the steps   (2 UAVs)          Fig. 13
target funnel by kind       targets_funnel    targets_funnel
=========================== ================= =================

Curves are the mean over the seeds with a band of one standard deviation; box plots show every
seed. The path figures reuse ``swarmplan.figures.plot_paths`` on the first seed of each
(scenario, algorithm). The target funnel (not in the paper) is the mean per run of each
stage of the runs' ``target_account``, by target kind (``swarmplan.figures.draw_funnel``).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from swarmplan.experiment_stats import groups
from swarmplan.figures import draw_funnel, plot_paths, plt, save

FIGURE_NUMBERS = {
    "efficiency": {
        "paths": 3,
        "coverage": 4,
        "engaged": 5,
        "coverage_metrics": 6,
        "engaged_box": 7,
        "separation": 13,
    },
    "swarm": {
        "paths": 8,
        "coverage": 9,
        "engaged": 10,
        "coverage_metrics": 11,
        "engaged_box": 12,
        "separation": 13,
    },
}
COLOURS = {"pso": "tab:green", "acoapf": "tab:orange", "hapf-aco": "tab:blue"}


def _colour(algorithm: str) -> str:
    return COLOURS.get(algorithm, "tab:gray")


def _curves(runs: Sequence[dict], key: str, scale: float = 1.0) -> np.ndarray:
    length = min(len(r[key]) for r in runs)
    return np.array(
        [[np.nan if v is None else float(v) * scale for v in r[key][:length]] for r in runs]
    )


def _by_scenario(results: Sequence[dict]) -> dict[str, list[tuple[str, list[dict]]]]:
    """(algorithm, runs) of each scenario, in canonical order."""
    out: dict[str, list[tuple[str, list[dict]]]] = {}
    for (scenario, algorithm), runs in groups(results).items():
        out.setdefault(scenario, []).append((algorithm, runs))
    return out


def plot_mean_curves(
    results: Sequence[dict], key: str, ylabel: str, title: str, path: Path, scale: float = 1.0
) -> Path:
    """Mean (and +-1 std band) over the seeds of a per-step curve, one panel per scenario."""
    scenarios = _by_scenario(results)
    fig, axes = plt.subplots(1, len(scenarios), figsize=(6 * len(scenarios), 4.2), squeeze=False)
    for ax, (scenario, per_algorithm) in zip(axes[0], scenarios.items(), strict=True):
        for algorithm, runs in per_algorithm:
            curves = _curves(runs, key, scale)
            mean, std = np.nanmean(curves, axis=0), np.nanstd(curves, axis=0)
            steps = np.arange(len(mean))
            ax.plot(steps, mean, color=_colour(algorithm), label=f"{algorithm} (n={len(runs)})")
            ax.fill_between(
                steps, mean - std, mean + std, color=_colour(algorithm), alpha=0.15, lw=0
            )
        ax.set_title(f"{scenario} ({per_algorithm[0][1][0]['uav_count']} UAVs)")
        ax.set_xlabel("decision step")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    return save(fig, path, dpi=110)


def plot_boxes(
    results: Sequence[dict], metrics: Sequence[tuple[str, str, float]], title: str, path: Path
) -> Path:
    """Box plots (every seed as a point) of per-run metrics: one panel per (metric, scenario)."""
    scenarios = _by_scenario(results)
    fig, axes = plt.subplots(
        len(metrics),
        len(scenarios),
        figsize=(5 * len(scenarios), 3.8 * len(metrics)),
        squeeze=False,
    )
    for row, (key, ylabel, scale) in enumerate(metrics):
        for col, (scenario, per_algorithm) in enumerate(scenarios.items()):
            ax = axes[row, col]
            names = [algorithm for algorithm, _ in per_algorithm]
            data = [
                [r[key] * scale for r in runs if r[key] is not None] for _, runs in per_algorithm
            ]
            ax.boxplot(data, tick_labels=names, showmeans=True)
            for k, values in enumerate(data):
                jitter = (
                    np.linspace(-0.12, 0.12, len(values))
                    if len(values) > 1
                    else np.zeros(len(values))
                )
                ax.plot(k + 1 + jitter, values, ".", color=_colour(names[k]), alpha=0.6, ms=4)
            ax.set_ylabel(ylabel)
            ax.set_title(scenario)
            ax.grid(alpha=0.3, axis="y")
    fig.suptitle(title)
    return save(fig, path, dpi=110)


def plot_separation(results: Sequence[dict], title: str, path: Path) -> Path:
    """Fig. 13: per step, the minimum distance between UAVs (lowest over the seeds, and its
    mean), the average nearest-neighbour distance, and the safety distance d_min."""
    grouped = groups(results)
    keys = list(grouped)
    cols = min(3, len(keys))
    rows = -(-len(keys) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.5 * cols, 3.8 * rows), squeeze=False)
    for ax, (scenario, algorithm) in zip(axes.ravel(), keys, strict=False):
        runs = grouped[(scenario, algorithm)]
        low = _curves(runs, "min_separation_curve")
        mean_nn = _curves(runs, "mean_min_separation_curve")
        steps = np.arange(low.shape[1])
        # steps where fewer than two UAVs fly are all-NaN slices: silence numpy's warnings
        with (
            np.errstate(all="ignore"),
            warnings.catch_warnings(action="ignore", category=RuntimeWarning),
        ):
            lines = (
                (np.nanmean(mean_nn, axis=0), "tab:blue", "average nearest distance"),
                (np.nanmean(low, axis=0), "tab:orange", "minimum distance (mean)"),
                (np.nanmin(low, axis=0), "tab:red", "minimum distance (lowest)"),
            )
        for curve, colour, label in lines:
            ax.plot(steps, curve, color=colour, lw=1, label=label)
        d_min = runs[0]["min_separation_limit_km"]
        ax.axhline(d_min, color="black", ls="--", lw=1, label=f"d_min = {d_min:g} km")
        ax.set_yscale("log")
        ax.set_title(f"{scenario} / {algorithm}", fontsize=9)
        ax.set_xlabel("decision step")
        ax.set_ylabel("distance (km)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    for ax in axes.ravel()[len(keys) :]:
        ax.set_visible(False)
    fig.suptitle(title)
    return save(fig, path, dpi=110)


def plot_target_funnels(results: Sequence[dict], title: str, path: Path) -> Path | None:
    """The target funnel by kind, mean per run, one panel per (scenario, algorithm); None when
    no run carries a target account."""
    panels = [(key, [r for r in runs if r.get("target_account")])
              for key, runs in groups(results).items()]  # fmt: skip
    panels = [(key, runs) for key, runs in panels if runs]
    if not panels:
        return None
    scenarios = list(dict.fromkeys(key[0] for key, _ in panels))
    algorithms = list(dict.fromkeys(key[1] for key, _ in panels))
    fig, axes = plt.subplots(len(scenarios), len(algorithms), squeeze=False,
                             figsize=(4.6 * len(algorithms), 3.6 * len(scenarios)))  # fmt: skip
    for ax in axes.ravel():
        ax.set_visible(False)
    for (scenario, algorithm), runs in panels:
        ax = axes[scenarios.index(scenario), algorithms.index(algorithm)]
        ax.set_visible(True)
        kinds = list(dict.fromkeys(k for r in runs for k in r["target_account"]["by_kind"]))
        mean = {
            kind: {
                stage: (
                    None if any(r["target_account"]["by_kind"].get(kind, {}).get(stage, 0) is None
                                for r in runs)
                    else sum(r["target_account"]["by_kind"].get(kind, {}).get(stage, 0)
                             for r in runs) / len(runs)
                )
                for stage in ("targets", "in_footprint", "seen", "pursued", "confirmed",
                              "engaged")
            }
            for kind in kinds
        }  # fmt: skip
        seen = sum(r["target_account"]["totals"]["seen"] for r in runs)
        engaged = sum(r["target_account"]["totals"]["engaged"] for r in runs)
        conversion = f"{engaged / seen:.2f}" if seen else "n/a"
        draw_funnel(ax, mean, f"{scenario} / {algorithm} ({len(runs)} runs): conversion "
                              f"{conversion}")  # fmt: skip
    axes[0, 0].legend(loc="upper right", fontsize=7)
    fig.suptitle(title)
    return save(fig, path, dpi=110)


def write_experiment_figures(
    experiment: str, results: Sequence[dict], path_runs: Sequence[dict], out_dir: Path
) -> list[Path]:
    """Every figure of ``experiment`` into ``out_dir``; ``path_runs`` are the runs (with their
    tracks) whose paths are drawn."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    n = FIGURE_NUMBERS[experiment]
    written = []
    for run in path_runs:
        name = (
            f"fig{n['paths']:02d}_paths_{run['scenario']}_{run['algorithm']}_seed{run['seed']}.png"
        )
        written.append(plot_paths(run, out_dir / name))
    written.append(
        plot_mean_curves(
            results,
            "coverage_curve",
            "coverage J_E (%)",
            f"Fig. {n['coverage']}: coverage over the decision steps",
            out_dir / f"fig{n['coverage']:02d}_coverage.png",
            scale=100,
        )
    )
    written.append(
        plot_mean_curves(
            results,
            "engaged_curve",
            "targets engaged",
            f"Fig. {n['engaged']}: targets engaged over the decision steps",
            out_dir / f"fig{n['engaged']:02d}_engaged.png",
        )
    )
    written.append(
        plot_boxes(
            results,
            [
                ("coverage", "coverage after the last step (%)", 100),
                ("coverage_slope_50", "slope over the first 50 steps (%/step)", 100),
            ],
            f"Fig. {n['coverage_metrics']}: coverage metrics",
            out_dir / f"fig{n['coverage_metrics']:02d}_coverage_metrics.png",
        )
    )
    written.append(
        plot_boxes(
            results,
            [("engaged_count", "targets engaged per run", 1)],
            f"Fig. {n['engaged_box']}: mission execution efficiency",
            out_dir / f"fig{n['engaged_box']:02d}_engaged_box.png",
        )
    )
    written.append(
        plot_separation(
            results,
            f"Fig. {n['separation']}: separation between UAVs",
            out_dir / f"fig{n['separation']:02d}_separation.png",
        )
    )
    funnel = plot_target_funnels(
        results,
        "Targets by kind: in a footprint, seen (>= 3 steps), pursued, confirmed, engaged "
        "(mean per run)",
        out_dir / "targets_funnel.png",
    )
    if funnel is not None:
        written.append(funnel)
    return written
