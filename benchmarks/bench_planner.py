"""Wall time of one 250-step offline run of each paper scenario, and per planning step per UAV.

python benchmarks/bench_planner.py [--repeat 3] [--seeds 1]
python benchmarks/bench_planner.py --against REV [--seeds 1 2 3 4 5]

``--against REV`` is the before/after comparison in one session: it checks REV (a commit, a
branch, ``HEAD~1``) out into a temporary git worktree and times the same runs there and here,
alternating between the two so that a change in the machine's load hits both, then prints both
and the ratio (here / REV), and whether both flew the same tracks, engagements and decision
modes on every seed ("same"; a change meant to keep the decisions must say so). Several seeds
average out that a planner change also changes the flown paths, and with them the work of each
step.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from revision_checkout import checked_out, flown_digest

SCENARIOS = ("paper-2uav", "paper-10uav", "paper-20uav")
REPO = Path(__file__).resolve().parents[1]


def time_runs(repeat: int, seeds: list[int]) -> dict[str, float]:
    """Per scenario, the mean over ``seeds`` of the best of ``repeat`` 250-step runs (s)."""
    return {name: s for name, (s, _) in timed_runs(repeat, seeds).items()}


def timed_runs(repeat: int, seeds: list[int]) -> dict[str, tuple[float, str]]:
    """Per scenario, ``time_runs``'s time and a digest of every seed's flown tracks,
    engagements and decision modes."""
    from planner.scenario import load_scenario
    from sim_gateway.offline_runner import run_offline

    out = {}
    for name in SCENARIOS:
        scenario = load_scenario(name)
        total, results = 0.0, []
        for seed in seeds:
            best = float("inf")
            for _ in range(repeat):
                started = time.perf_counter()
                result = run_offline(scenario, seed, 250)
                best = min(best, time.perf_counter() - started)
            total += best
            results.append(result)
        out[name] = (total / len(seeds), flown_digest(results))
    return out


def time_in(tree: Path, repeat: int, seeds: list[int]) -> dict[str, list]:
    """``time_runs`` in a fresh interpreter on the code of ``tree``."""
    code = (
        "import json, sys; sys.path.insert(0, sys.argv[1]); sys.path.insert(0, sys.argv[2]);"
        "from bench_planner import timed_runs;"
        "print(json.dumps(timed_runs(int(sys.argv[3]), json.loads(sys.argv[4]))))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(tree), str(Path(__file__).parent), str(repeat),
         json.dumps(seeds)],
        capture_output=True, text=True, cwd=tree, check=False,
    )  # fmt: skip
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        raise SystemExit(f"bench_planner: the run on {tree} failed: {last}")
    return json.loads(proc.stdout)


def uav_count(name: str) -> int:
    from planner.scenario import load_scenario

    return load_scenario(name).uav_count


def compare(rev: str, repeat: int, seeds: list[int], rounds: int) -> None:
    before = {name: [] for name in SCENARIOS}
    after = {name: [] for name in SCENARIOS}
    tracks: dict[str, set[str]] = {name: set() for name in SCENARIOS}
    with checked_out(rev, "bench_planner") as tree:
        for _ in range(rounds):  # alternate, so that a change of load hits both
            for name, (s, digest) in time_in(tree, repeat, seeds).items():
                before[name].append(s)
                tracks[name].add(digest)
            for name, (s, digest) in time_in(REPO, repeat, seeds).items():
                after[name].append(s)
                tracks[name].add(digest)
    print(f"planner time per decision step (ms; best of {repeat}, mean over seeds {seeds}, "
          f"best of {rounds} alternating rounds)")  # fmt: skip
    print(f"{'scenario':<12} {'UAVs':>4} {rev[:12]:>12} {'this tree':>10} {'ratio':>7}"
          f" {'tracks':>7}")  # fmt: skip
    for name in SCENARIOS:
        b, a = min(before[name]) / 250 * 1000, min(after[name]) / 250 * 1000
        same = "same" if len(tracks[name]) == 1 else "DIFFER"
        print(f"{name:<12} {uav_count(name):>4} {b:>12.2f} {a:>10.2f} {a / b:>7.2f} {same:>7}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seeds", type=int, nargs="+", default=None)
    parser.add_argument("--against", metavar="REV", help="also time this git revision, A/B")
    parser.add_argument("--rounds", type=int, default=2, help="A/B rounds with --against")
    args = parser.parse_args()
    if args.repeat < 1 or args.rounds < 1:
        parser.error("--repeat and --rounds must be at least 1")
    if args.against:
        compare(args.against, args.repeat, args.seeds or [1, 2, 3, 4, 5], args.rounds)
        return
    seeds = args.seeds or [1]
    print(
        f"{'scenario':<12} {'UAVs':>4} {'run (s)':>9} {'per step (ms)':>14}"
        f" {'per step per UAV (ms)':>22}"
    )
    baseline = None
    for name, best in time_runs(args.repeat, seeds).items():
        n = uav_count(name)
        per_step = best / 250 * 1000
        baseline = baseline or per_step / n
        print(f"{name:<12} {n:>4} {best:>9.2f} {per_step:>14.2f} {per_step / n:>22.3f}"
              f"   ({per_step / n / baseline:.2f}x the 2-UAV cost per UAV)")  # fmt: skip


if __name__ == "__main__":
    main()
