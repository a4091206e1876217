"""Fly ArduPlane SITL planes with the payload simulator over a whole mission and print its numbers.

Needs ``ARDUPLANE_SITL`` (the binary; ../shared/sitl/arduplane here). Example, the issue-11
figures of docs/sitl.md (5 planes over arduplane-3uav's 40 steps; at 5x ~9-10 min wall, at 10x
~6-7; the daemon refuses a speedup the machine cannot keep, and says which one it can)::

    ARDUPLANE_SITL=../shared/sitl/arduplane nice -n 10 python benchmarks/bench_sitl.py \\
        --planes 5 --speedup 5

PX4 SITL's SIH airplanes instead (``PX4_SITL``; ../shared/sitl/px4 here), on the built-in
``px4-3uav`` with its own three planes (docs/px4.md)::

    PX4_SITL=../shared/sitl/px4 nice -n 10 python benchmarks/bench_sitl.py --autopilot px4 \
        --speedup 5

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

import px4_harness  # noqa: E402
from px4_mission import fly_px4_mission  # noqa: E402
from sitl_harness import sitl_binary_from_env, skip_reason  # noqa: E402
from sitl_mission import fly_sitl_mission, measure  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--autopilot", choices=("arduplane", "px4"), default="arduplane")
    parser.add_argument("--planes", type=int, default=5, help="ArduPlane; PX4: the scenario's")
    parser.add_argument("--speedup", type=float, default=10.0, help="SITL --speedup (1: real time)")
    parser.add_argument("--scenario", default=None, help="default arduplane-3uav / px4-3uav")
    parser.add_argument("--steps", type=int, default=None, help="default: the scenario's")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--timeout", type=float, default=None, help="wall s (default: ample)")
    parser.add_argument(
        "--keep", type=Path, default=None,
        help="keep the run's files here (out/: result.json, mission.tlog; daemon.log, payload.log)",
    )  # fmt: skip
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    px4 = args.autopilot == "px4"
    args.scenario = args.scenario or ("px4-3uav" if px4 else "arduplane-3uav")
    binary = px4_harness.px4_root_from_env() if px4 else sitl_binary_from_env()
    if binary is None:
        why = px4_harness.skip_reason() if px4 else skip_reason()
        print(f"bench_sitl: {why}", file=sys.stderr)
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
        if px4:
            run = fly_px4_mission(
                binary, workdir, args.scenario, speedup=args.speedup, steps=args.steps,
                seed=args.seed, timeout_s=timeout,
            )  # fmt: skip
        else:
            run = fly_sitl_mission(
                binary, workdir, planes=args.planes, speedup=args.speedup,
                scenario=args.scenario, steps=args.steps, seed=args.seed, timeout_s=timeout,
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
