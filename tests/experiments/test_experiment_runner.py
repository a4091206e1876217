"""``swarmplan experiment``: the statistics match a hand computation from the per-run JSONs,
and the CSVs are byte-identical on a rerun, in-process, over local processes and on Dask."""

import csv
import json
import math
import statistics
from pathlib import Path

import distributed
import numpy as np
import pytest
from scipy.stats import chi2, rankdata

from swarmplan.cli import main as swarmplan

CSVS = ("runs.csv", "summary.csv", "friedman.csv")
SMALL = ["experiment", "efficiency", "--runs", "3", "--steps", "40", "--seed-base", "5", "--quiet"]


@pytest.fixture(scope="module")
def local_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("local")
    assert swarmplan([*SMALL, "--jobs", "2", "--out", str(out)]) == 0
    return out


def per_run_results(out: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((out / "runs").rglob("seed-*.json"))]


def read_csv(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def friedman_by_hand(samples: list[list[float]]) -> tuple[float, float]:
    """Friedman's chi-square with the tie correction, from ranks within each block (seed)."""
    data = np.array(samples, dtype=float).T  # blocks x treatments
    n, k = data.shape
    ranks = np.array([rankdata(row) for row in data])
    r = ranks.sum(axis=0)
    stat = 12.0 / (n * k * (k + 1)) * np.sum(r**2) - 3.0 * n * (k + 1)
    ties = sum(np.sum(c**3 - c) for row in data for c in [np.unique(row, return_counts=True)[1]])
    correction = 1.0 - ties / (n * k * (k * k - 1))
    if correction == 0:
        return math.nan, math.nan
    stat /= correction
    return stat, chi2.sf(stat, k - 1)


def test_writes_every_output(local_run):
    results = per_run_results(local_run)
    assert len(results) == 9  # 3 algorithms x 1 scenario x 3 seeds
    assert {(r["algorithm"], r["seed"]) for r in results} == {
        (a, s) for a in ("pso", "acoapf", "hapf-aco") for s in (5, 6, 7)
    }
    assert all(r["steps"] == 40 and r["scenario"] == "paper-2uav" for r in results)
    figures = sorted(p.name for p in (local_run / "figures").glob("*.png"))
    for fig in (
        "fig04_coverage",
        "fig05_engaged",
        "fig06_coverage_metrics",
        "fig07_engaged_box",
        "fig13_separation",
    ):
        assert f"{fig}.png" in figures
    assert sum(name.startswith("fig03_paths_") for name in figures) == 3
    report = (local_run / "report.md").read_text()
    assert "wall time" in report and "Friedman" in report and "5.5" in report  # the paper's number
    # the target funnel by kind: a figure, shown in the report
    assert "targets_funnel.png" in figures
    assert "![Target funnel by kind](figures/targets_funnel.png)" in report


def test_statistics_match_a_hand_computation_from_the_run_files(local_run):
    results = per_run_results(local_run)
    summary = {
        (row["scenario"], row["algorithm"]): row for row in read_csv(local_run / "summary.csv")
    }
    for (scenario, algorithm), row in summary.items():
        runs = [r for r in results if r["scenario"] == scenario and r["algorithm"] == algorithm]
        assert int(row["runs"]) == len(runs) == 3
        for metric in ("engaged_count", "coverage", "coverage_slope_50", "min_separation_km"):
            values = [r[metric] for r in runs]
            assert float(row[f"{metric}_mean"]) == pytest.approx(statistics.mean(values), abs=1e-6)
            assert float(row[f"{metric}_std"]) == pytest.approx(statistics.stdev(values), abs=1e-6)
        assert int(row["violations_separation"]) == sum(r["violations"]["separation"] for r in runs)

    tests = {row["metric"]: row for row in read_csv(local_run / "friedman.csv")}
    assert set(tests) == {"engaged_count", "coverage", "coverage_slope_50"}
    for metric, row in tests.items():
        samples = [
            [r[metric] for r in sorted(results, key=lambda r: r["seed"]) if r["algorithm"] == a]
            for a in ("pso", "acoapf", "hapf-aco")
        ]
        stat, p = friedman_by_hand(samples)
        if math.isnan(stat):
            assert row["chi2"] == "" and row["p_value"] == ""
        else:
            assert float(row["chi2"]) == pytest.approx(stat, abs=1e-5)
            assert float(row["p_value"]) == pytest.approx(p, rel=1e-5)
    assert any(row["chi2"] for row in tests.values())  # coverage differs between algorithms

    rows = read_csv(local_run / "runs.csv")
    assert [(r["algorithm"], int(r["seed"])) for r in rows] == [
        (a, s) for a in ("pso", "acoapf", "hapf-aco") for s in (5, 6, 7)
    ]


def test_rerun_in_process_gives_byte_identical_csvs(local_run, tmp_path):
    assert swarmplan([*SMALL, "--jobs", "1", "--out", str(tmp_path)]) == 0
    for name in CSVS:
        assert (tmp_path / name).read_bytes() == (local_run / name).read_bytes(), name


@pytest.mark.timeout(120)
def test_dask_local_cluster_gives_byte_identical_csvs(local_run, tmp_path):
    with distributed.LocalCluster(
        n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None
    ) as cluster:
        assert swarmplan([*SMALL, "--dask", cluster.scheduler_address, "--out", str(tmp_path)]) == 0
    for name in CSVS:
        assert (tmp_path / name).read_bytes() == (local_run / name).read_bytes(), name
    assert "Dask cluster" in (tmp_path / "report.md").read_text()
