"""Fly ArduPlane SITL planes with the payload simulator over a whole mission and print its numbers.

Needs ``ARDUPLANE_SITL`` (the binary; ../shared/sitl/arduplane here). Example, the issue-11
figures of docs/sitl.md (5 planes over arduplane-3uav's 40 steps; at 5x ~9-10 min wall, at 10x
~6-7; the daemon refuses a speedup the machine cannot keep, and says which one it can)::

    ARDUPLANE_SITL=../shared/sitl/arduplane nice -n 10 python benchmarks/bench_sitl.py \\
        --planes 5 --speedup 5

Prints one line per number: time to ready, coverage, engaged, violations, minimum separation
(from the telemetry at the decision steps), distance from the planned cell centre at the next
decision (mean / 95th percentile / worst), looks, late steps, decision-step length on the
vehicles' clock (mean, min, max, worst drift from step_s), the safety account along every
position report per phase (mission / hold / failsafe / RTL), the vehicles lost and back, who was
sent home, the machine's load average (start, mean, max) and wall time; ``--json`` prints them
as one JSON object instead. Every process it starts is stopped at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO / "tests"), str(REPO / "tests" / "sitl")]

from sitl_harness import sitl_binary_from_env, skip_reason  # noqa: E402
from sitl_mission import fly_sitl_mission, measure  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--planes", type=int, default=5)
    parser.add_argument("--speedup", type=float, default=10.0, help="SITL --speedup (1: real time)")
    parser.add_argument("--scenario", default="arduplane-3uav")
    parser.add_argument("--steps", type=int, default=None, help="default: the scenario's")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--timeout", type=float, default=None, help="wall s (default: ample)")
    parser.add_argument(
        "--keep", type=Path, default=None,
        help="keep the run's files here (out/: result.json, mission.tlog; daemon.log, payload.log)",
    )  # fmt: skip
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    binary = sitl_binary_from_env()
    if binary is None:
        print(f"bench_sitl: {skip_reason()}", file=sys.stderr)
        return 2
    from planner.scenario import load_scenario

    cfg_steps = args.steps or load_scenario(args.scenario).steps
    step_s = load_scenario(args.scenario).config.step_s
    # boot + take-off + the steps + the flight home, on the vehicles' clock, and a margin
    timeout = args.timeout or 120 + (400 + cfg_steps * step_s) / args.speedup * 1.5
    loads, done = [os.getloadavg()[0]], threading.Event()

    def sample_load() -> None:  # the machine is shared: its load beside the run, every 10 s
        while not done.wait(10.0):
            loads.append(os.getloadavg()[0])

    threading.Thread(target=sample_load, daemon=True).start()
    with tempfile.TemporaryDirectory(prefix="bench-sitl-") as tmp:
        workdir = args.keep or Path(tmp)
        run = fly_sitl_mission(
            binary, workdir, planes=args.planes, speedup=args.speedup, scenario=args.scenario,
            steps=args.steps, seed=args.seed, timeout_s=timeout,
        )  # fmt: skip
        numbers = measure(run)
    done.set()
    loads.append(os.getloadavg()[0])
    numbers["load_average"] = {  # 1-minute averages
        "start": round(loads[0], 1),
        "mean": round(sum(loads) / len(loads), 1),
        "max": round(max(loads), 1),
    }
    if args.json:
        print(json.dumps(numbers))
    else:
        for key, value in numbers.items():
            print(f"{key:26s} {value}")
    if run.returncode != 0:
        print(run.explain(), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
