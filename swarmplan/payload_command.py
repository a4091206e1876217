"""``swarmplan payload``: the world and each vehicle's camera for autopilots that run elsewhere.

Example, three ArduPlane SITL instances (docs/sitl.md)::

    swarmplan payload --scenario arduplane-3uav --seed 1 \\
        --connect tcp:127.0.0.1:5762 --connect tcp:127.0.0.1:5772 --connect tcp:127.0.0.1:5782

It prints one start line, a progress line every 5 s, and a JSON summary (looks, engagement
requests, the targets engaged in ground truth) on exit (Ctrl-C, SIGTERM or ``--duration-s``).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import threading
import time

os.environ.setdefault("MAVLINK20", "1")

from planner.errors import UserError  # noqa: E402
from planner.scenario import load_scenario  # noqa: E402
from swarmplan import option_groups  # noqa: E402
from swarmplan.arguments import endpoint, positive_float  # noqa: E402

HELP = (
    "simulate only the world and each vehicle's camera (component 100) for external autopilots "
    "such as ArduPlane SITL"
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    option_groups.add_world_arguments(
        parser, "arduplane-3uav", "seed of the world (sensor noise, target motion)"
    )
    parser.add_argument(
        "--connect",
        action="append",
        required=True,
        type=endpoint,
        metavar="ENDPOINT",
        help="where an autopilot's telemetry is heard and its camera speaks: tcp:HOST:PORT "
        "(ArduPilot SITL instance i: SERIAL1 on 5762+10i), udpin:HOST:PORT or udpout:HOST:PORT; "
        "repeatable",
    )
    parser.add_argument(
        "--min-look-altitude",
        type=positive_float,
        default=10.0,
        metavar="M",
        help="a vehicle looks only when armed and at least this far above home (default 10 m)",
    )
    option_groups.add_duration_option(parser, "wall")
    option_groups.add_quiet_option(parser)
    option_groups.add_target_account_option(parser)


def main(args: argparse.Namespace) -> int:
    from sim_gateway.payload_simulator import PayloadOptions, PayloadSimulator

    scenario = load_scenario(args.scenario)
    if args.vehicles is not None and not 1 <= args.vehicles <= 250:
        raise UserError(f"--vehicles {args.vehicles} must be 1..250")
    options = PayloadOptions(
        seed=args.seed, vehicles=args.vehicles, min_look_altitude_m=args.min_look_altitude
    )
    with PayloadSimulator(scenario, args.connect, options) as payload:
        n = len(payload.cameras)
        print(
            f"payload: world of scenario {scenario.name!r}, seed {options.seed}; cameras of "
            f"{n} vehicles (sysid 1..{n}, component 100) on {', '.join(args.connect)}; looks "
            f"every {scenario.config.step_s:g} s of each vehicle's clock",
            flush=True,
        )

        def progress(p: PayloadSimulator) -> None:
            if not args.quiet:
                print(p.progress_line(), flush=True)

        # SIGTERM and Ctrl-C end the loop between two messages (never inside one's handling)
        stopping = threading.Event()
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, lambda *_: stopping.set())
        end = None if args.duration_s is None else time.monotonic() + args.duration_s

        def over() -> bool:
            return stopping.is_set() or (end is not None and time.monotonic() >= end)

        payload.run(until=over, on_progress=progress)
        print(json.dumps(payload.summary()), flush=True)
        if args.target_account is not None:
            from swarmplan.sim_command import write_target_truth

            write_target_truth(payload.target_account, args.target_account)
    return 0
