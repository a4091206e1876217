"""The planner's cost against swarm size and area: CPU time per decision step and peak memory.

python benchmarks/bench_scale.py [--uavs 2 10 20 50 100 250 500] [--cells 100 200 400]
                                 [--steps 40] [--max-gb 6] [--figure scale.png]
python benchmarks/bench_scale.py --against REV [...]

Each point is a copy of paper-20uav (its targets and threats, random starts) with ``uavs.count``
and ``grid_nx = grid_ny = cells`` changed (cells of 1 km), run offline (``run_offline``) for
``--steps`` decision steps in a fresh interpreter of its own, so that its peak memory (the
process's maximum resident set) is its own. It prints, per point, the CPU time of the first
step (building the swarm's beliefs and safety models), the mean CPU time of the steps after it,
the peak memory and a digest of the flown tracks, engagements and decision modes; ``--figure``
draws the table (matplotlib). A point whose memory, scaled from the smaller points measured,
would pass ``--max-gb`` is skipped and said so. Run 40 steps
or more: the cost grows as the UAVs find threats (each set of known threats gets safety models
of its own, with fields per home) and as they turn home (the run's steps are its mission, so
``home_by_end`` brings them home within it); docs/results.md "Swarm size" has the table.

``--against REV`` runs the same points on REV (a commit or branch, checked out into a temporary
git worktree) and here, one after the other, and prints both, the ratios (here / REV) and
whether the two flew the same tracks and engagements (a change meant to keep the decisions must
say "same").
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from revision_checkout import checked_out

REPO = Path(__file__).resolve().parents[1]

#: run in a fresh interpreter: argv = tree, benchmarks folder, uavs, cells, steps; prints one
#: JSON line
_POINT = """
import dataclasses, json, resource, sys, time
sys.path[:0] = [sys.argv[1], sys.argv[2]]
from planner.scenario import load_scenario
from revision_checkout import flown_digest
from sim_gateway.offline_runner import run_offline
uavs, cells, steps = (int(a) for a in sys.argv[3:6])
scenario = load_scenario("paper-20uav")
scenario = scenario.with_config(grid_nx=cells, grid_ny=cells)
scenario = dataclasses.replace(scenario, uav_count=uavs)
cpu = []
class Clock:
    def __init__(self): self.last = time.process_time()
    def __call__(self, *args, **kwargs):
        now = time.process_time(); cpu.append(now - self.last); self.last = now
clock = Clock()
result = run_offline(scenario, 1, steps, account=False, progress=clock)
peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"first_s": cpu[0], "step_s": sum(cpu[1:]) / max(1, len(cpu) - 1),
                  "peak_mb": peak_mb, "violations": result["violations"],
                  "tracks": flown_digest([result])}))
"""


def measure(tree: Path, uavs: int, cells: int, steps: int) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", _POINT, str(tree), str(Path(__file__).parent), str(uavs),
         str(cells), str(steps)],
        capture_output=True, text=True, cwd=tree, check=False,
    )  # fmt: skip
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        return {"error": last}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def estimate_gb(done: dict[tuple[int, int], dict], uavs: int, cells: int) -> float | None:
    """Peak memory of (uavs, cells) scaled from the largest measured point below it: memory
    grows with UAVs x cells (every UAV holds maps of every cell)."""
    below = [(u, c) for (u, c), r in done.items() if "peak_mb" in r and u <= uavs and c <= cells]
    if not below:
        return None
    u, c = max(below, key=lambda uc: uc[0] * uc[1] ** 2)
    return done[(u, c)]["peak_mb"] / 1024 * (uavs / u) * (cells / c) ** 2


def sweep(tree: Path, args: argparse.Namespace) -> dict[tuple[int, int], dict]:
    done: dict[tuple[int, int], dict] = {}
    for cells in args.cells:
        for uavs in args.uavs:
            guess = estimate_gb(done, uavs, cells)
            if guess is not None and guess > args.max_gb:
                done[(uavs, cells)] = {"skipped_gb": guess}
                continue
            done[(uavs, cells)] = measure(tree, uavs, cells, args.steps)
            print(f"  {uavs:>4} UAVs, {cells} x {cells}: {_cell(done[(uavs, cells)])}",
                  file=sys.stderr, flush=True)  # fmt: skip
    return done


def _cell(r: dict) -> str:
    if "error" in r:
        return f"failed: {r['error']}"
    if "skipped_gb" in r:
        return f"skipped (~{r['skipped_gb']:.0f} GB)"
    return f"{r['step_s'] * 1000:9.1f} ms/step {r['first_s']:7.2f} s first {r['peak_mb']:7.0f} MB"


def print_table(points: dict[tuple[int, int], dict], title: str) -> None:
    print(title)
    print(f"{'UAVs':>5} {'cells':>9} {'CPU per step':>13} {'first step':>11} {'peak memory':>12}")
    for (uavs, cells), r in sorted(points.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        if "peak_mb" in r:
            print(f"{uavs:>5} {cells:>4} x {cells:<3} {r['step_s'] * 1000:>10.1f} ms"
                  f" {r['first_s']:>9.2f} s {r['peak_mb']:>9.0f} MB")  # fmt: skip
        else:
            print(f"{uavs:>5} {cells:>4} x {cells:<3} {_cell(r):>37}")


def draw(points: dict[tuple[int, int], dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (cpu_ax, mem_ax) = plt.subplots(1, 2, figsize=(10, 4))
    for cells in sorted({c for _, c in points}):
        row = sorted((u, r) for (u, c), r in points.items() if c == cells and "peak_mb" in r)
        if not row:
            continue
        label = f"{cells} x {cells} cells"
        cpu_ax.plot([u for u, _ in row], [r["step_s"] * 1000 for _, r in row], "o-", label=label)
        mem_ax.plot([u for u, _ in row], [r["peak_mb"] for _, r in row], "o-", label=label)
    for ax, what in ((cpu_ax, "CPU time per decision step (ms)"), (mem_ax, "peak memory (MB)")):
        ax.set(xscale="log", yscale="log", xlabel="UAVs", ylabel=what)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle("HAPF-ACO planner cost against swarm size (paper-20uav copies, offline)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"figure: {path}")


def compare(rev: str, args: argparse.Namespace) -> None:
    with checked_out(rev, "bench_scale") as tree:
        before, after = sweep(tree, args), sweep(REPO, args)
    print(f"{'UAVs':>5} {'cells':>9} {'ms/step ' + rev[:10]:>20} {'here':>8} {'ratio':>6}"
          f" {'MB ' + rev[:10]:>14} {'here':>7} {'ratio':>6} {'tracks':>9}")  # fmt: skip
    for key in sorted(after, key=lambda k: (k[1], k[0])):
        b, a = before.get(key, {}), after[key]
        if "peak_mb" not in a or "peak_mb" not in b:
            continue
        print(f"{key[0]:>5} {key[1]:>4} x {key[1]:<3} {b['step_s'] * 1000:>20.1f}"
              f" {a['step_s'] * 1000:>8.1f} {a['step_s'] / b['step_s']:>6.2f}"
              f" {b['peak_mb']:>14.0f} {a['peak_mb']:>7.0f} {a['peak_mb'] / b['peak_mb']:>6.2f}"
              f" {'same' if a['tracks'] == b['tracks'] else 'DIFFER':>9}")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--uavs", type=int, nargs="+", default=[2, 10, 20, 50, 100, 250, 500])
    parser.add_argument("--cells", type=int, nargs="+", default=[100, 200, 400])
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--max-gb", type=float, default=6.0)
    parser.add_argument("--figure", type=Path, help="draw the table into this PNG")
    parser.add_argument("--against", metavar="REV", help="also measure this git revision, A/B")
    args = parser.parse_args()
    if args.steps < 2 or min(args.uavs) < 1 or min(args.cells) < 20:
        parser.error("--steps must be at least 2, --uavs at least 1 and --cells at least 20")
    if args.against:
        compare(args.against, args)
        return
    points = sweep(REPO, args)
    print_table(points, f"planner cost, {args.steps} decision steps per point")
    if args.figure:
        draw(points, args.figure)


if __name__ == "__main__":
    main()
