"""End-to-end benchmark: the full paper 10-UAV scenario flown over loopback UDP MAVLink
(`swarmplan demo`: simulator subprocess + daemon) next to the offline run of the same seed.

    python benchmarks/bench_end_to_end.py [--seeds 1 2 3] [--speedup 100] [--steps 250]

Prints wall time, coverage, engaged count/value, returned, minimum separation and violations.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def swarmplan_json(args: list[str]) -> dict:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run(
        [sys.executable, "-m", "swarmplan", *args, "--json"],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO,
        timeout=900,
    )
    if proc.returncode != 0:
        raise SystemExit(
            f"swarmplan {' '.join(args)} failed: {proc.stderr.strip().splitlines()[-1:]}"
        )
    return json.loads(proc.stdout)


def row(kind: str, seed: int, r: dict) -> str:
    v = r["violations"]
    sep = r["min_separation_km"]
    return (
        f"{kind:<8} {seed:>4} {r['wall_time_s']:>8.1f} {100 * r['coverage']:>8.1f} "
        f"{r['engaged_count']:>7} "
        f"{r['engaged_value']:>6g} {r['returned_count']:>8} "
        f"{'-' if sep is None else f'{sep:.2f}':>7} "
        f"{v['threat']:>6} {v['separation']:>4} {v['turn']:>4} {v['range']:>5}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="paper-10uav")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1])
    parser.add_argument("--speedup", type=float, default=100.0)
    parser.add_argument("--steps", type=int, default=None)
    args = parser.parse_args()
    steps = ["--steps", str(args.steps)] if args.steps else []
    print(
        f"{'run':<8} {'seed':>4} {'wall s':>8} {'cover %':>8} {'engaged':>7} {'value':>6} "
        f"{'returned':>8} "
        f"{'min sep':>7} {'threat':>6} {'sep':>4} {'turn':>4} {'range':>5}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            offline = swarmplan_json(
                ["run", args.scenario, "--seed", str(seed), *steps, "--out", f"{tmp}/off{seed}"]
            )
            print(row("offline", seed, offline), flush=True)
            e2e = swarmplan_json(
                [
                    "demo",
                    args.scenario,
                    "--seed",
                    str(seed),
                    *steps,
                    "--speedup",
                    f"{args.speedup:g}",
                    "--out",
                    f"{tmp}/e2e{seed}",
                ]
            )
            print(row("mavlink", seed, e2e), flush=True)
            print(
                f"{'':<13} overrides {e2e.get('envelope_overrides')} lost {e2e.get('lost_uavs')} "
                f"refused {e2e.get('refused_commands')}",
                flush=True,
            )


if __name__ == "__main__":
    main()
