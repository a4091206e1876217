"""``swarmplan radio-relay``: the planes' telemetry radio between real autopilots, standing in
for the radios of a swarm of companion computers (``sim_gateway/radio_relay.py``,
docs/onboard.md "On a companion computer").

Example, three ArduPlane SITL instances (SERIAL0 of instance N on TCP 5760 + 10 N)::

    swarmplan radio-relay --connect tcp:127.0.0.1:5760 --connect tcp:127.0.0.1:5770 \\
        --connect tcp:127.0.0.1:5780 --radio-range-km 20 --radio-loss 0.1

It relays only the swarm link's frames, between the planes the radio model lets hear each
other. It prints one start line, a progress line every 5 s, and a JSON summary (the radio's
counts, what it kept off the air) on exit (Ctrl-C, SIGTERM or ``--duration-s``).
"""

from __future__ import annotations

import argparse
import json
import signal
import threading
import time

from swarmplan import option_groups
from swarmplan.arguments import endpoint
from swarmplan.sim_command import add_radio_arguments, radio_options

HELP = "the swarm link's radio between real autopilots' telemetry ports (range, loss), counted"
PROGRESS_S = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--connect", action="append", required=True, type=endpoint, metavar="ENDPOINT",
        help="a plane's telemetry port, where its autopilot forwards its node's frames: "
        "tcp:HOST:PORT (ArduPilot SITL instance N: SERIAL0 on 5760+10N), udpin:HOST:PORT or "
        "udpout:HOST:PORT; one per plane",
    )  # fmt: skip
    option_groups.add_seed_argument(parser, "seed of the radio's losses")
    add_radio_arguments(parser)
    option_groups.add_duration_option(parser, "wall")
    option_groups.add_quiet_option(parser)


def main(args: argparse.Namespace) -> int:
    from sim_gateway.radio_relay import RELAY_SYSTEM_ID, RadioRelay

    options = radio_options(args)
    options.validate()
    with RadioRelay(args.connect, options, args.seed) as relay:
        print(
            f"radio-relay: {len(args.connect)} planes on {', '.join(args.connect)}; range "
            f"{options.range_km:g} km, loss {options.loss:g}; swarm-link frames only; its own "
            f"heartbeat as system {RELAY_SYSTEM_ID}",
            flush=True,
        )
        stopping = threading.Event()
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, lambda *_: stopping.set())
        end = None if args.duration_s is None else time.monotonic() + args.duration_s
        next_progress = time.monotonic() + PROGRESS_S
        while not stopping.is_set() and (end is None or time.monotonic() < end):
            relay.poll()
            if not args.quiet and time.monotonic() >= next_progress:
                next_progress += PROGRESS_S
                print(relay.progress_line(), flush=True)
        print(json.dumps(relay.summary()), flush=True)
    return 0
