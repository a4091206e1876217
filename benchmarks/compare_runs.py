"""Two sets of runs of the same seeds, before and after a change, side by side: per scenario and
algorithm, coverage, engaged and home at the end (mean, sd, min, max of each), the mean
difference, Welch's t-test and a paired bootstrap 95 % interval of the difference, and how many
seeds changed at all.

python benchmarks/compare_runs.py BEFORE/runs.csv AFTER/runs.csv [BEFORE2 AFTER2 ...]

The ``runs.csv`` files are ``swarmplan experiment``'s (docs/experiments.md), e.g.::

    swarmplan experiment efficiency --runs 30 --algorithms hapf-aco --out before-efficiency
"""

from __future__ import annotations

import csv
import sys
from collections import defaultdict

import numpy as np
from scipy import stats

METRICS = (("coverage", "coverage %", 100.0), ("engaged_count", "engaged", 1.0),
           ("returned_count", "home", 1.0))  # fmt: skip


def read(path: str) -> dict[tuple[str, str], dict[int, dict[str, str]]]:
    """Rows of a runs.csv by (scenario, algorithm) and seed."""
    out: dict[tuple[str, str], dict[int, dict[str, str]]] = defaultdict(dict)
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            out[(row["scenario"], row["algorithm"])][int(row["seed"])] = row
    return out


def summary(values: np.ndarray) -> str:
    return (f"{values.mean():.2f} ± {values.std(ddof=1):.2f} "
            f"[{values.min():.2f}, {values.max():.2f}]")  # fmt: skip


def paired_bootstrap(diff: np.ndarray, draws: int = 10000) -> tuple[float, float]:
    """95 % interval of the mean of ``diff`` (seeds resampled, fixed generator)."""
    rng = np.random.default_rng(0)
    means = diff[rng.integers(0, len(diff), (draws, len(diff)))].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return float(low), float(high)


def main(paths: list[str]) -> None:
    if len(paths) < 2 or len(paths) % 2:
        sys.exit("give runs.csv files in pairs: BEFORE AFTER [BEFORE AFTER ...]")
    before: dict = {}
    after: dict = {}
    for b, a in zip(paths[::2], paths[1::2], strict=True):
        before.update(read(b))
        after.update(read(a))
    print("| scenario | algorithm | metric | before: mean ± sd [min, max] | after | difference "
          "| Welch p | bootstrap 95 % CI | seeds changed |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for key in sorted(before.keys() & after.keys()):
        seeds = sorted(before[key].keys() & after[key].keys())
        for column, name, scale in METRICS:
            x = np.array([float(before[key][s][column]) for s in seeds]) * scale
            y = np.array([float(after[key][s][column]) for s in seeds]) * scale
            diff = y - x
            changed = int((diff != 0).sum())
            if np.all(x == y) or (x.std() == 0 and y.std() == 0):
                p = "—"
            else:
                p = f"{stats.ttest_ind(y, x, equal_var=False).pvalue:.2f}"
            low, high = paired_bootstrap(diff)
            print(f"| {key[0]} | {key[1]} | {name} | {summary(x)} | {summary(y)} | "
                  f"{diff.mean():+.2f} | {p} | [{low:+.2f}, {high:+.2f}] | "
                  f"{changed} of {len(seeds)} |")  # fmt: skip


if __name__ == "__main__":
    main(sys.argv[1:])
