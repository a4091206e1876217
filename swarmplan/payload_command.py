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
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")

from planner.errors import UserError  # noqa: E402
from planner.scenario import load_scenario  # noqa: E402
from swarmplan.arguments import (  # noqa: E402
    OneLineParser,
    add_seed_argument,
    positive_float,
    positive_int,
)

HELP = (
    "simulate only the world and each vehicle's camera (component 100) for external autopilots "
    "such as ArduPlane SITL"
)


def _endpoint(text: str) -> str:
    """An endpoint spec that parses (``tcp:HOST:PORT``, ``udpin:...``, ``udpout:...``)."""
    from mavlink_wire.links import EndpointError, parse_endpoint

    try:
        parse_endpoint(text)
    except EndpointError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--connect ")) from None
    return text


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scenario", default="arduplane-3uav", help="built-in scenario name or TOML file"
    )
    add_seed_argument(parser, "seed of the world (sensor noise, target motion)")
    parser.add_argument(
        "--vehicles",
        type=positive_int,
        default=None,
        help="number of vehicles (default: the scenario's)",
    )
    parser.add_argument(
        "--connect",
        action="append",
        required=True,
        type=_endpoint,
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
    parser.add_argument(
        "--duration-s", type=positive_float, default=None, help="stop after this many wall s"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    parser.add_argument(
        "--target-account", type=Path, default=None, metavar="PATH",
        help="on exit, write the ground-truth half of the per-target account as JSON; "
        "swarmplan account joins it to the daemon's result.json (docs/experiments.md)",
    )  # fmt: skip


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


def run_standalone(argv: list[str] | None = None) -> int:
    """``python -m swarmplan.payload_command`` without the swarmplan wrapper."""
    parser = OneLineParser(prog="payload", description=HELP)
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return main(args)
    except UserError as exc:
        print(f"payload: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(run_standalone())
