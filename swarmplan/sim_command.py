"""``swarmplan sim``: start N simulated ArduPlanes that speak MAVLink 2 over UDP.

Example: ``swarmplan sim --scenario paper-10uav --seed 3 --speedup 50`` then point a ground
station or the planner daemon at UDP port 14550 (``mavproxy.py --master=udpin:127.0.0.1:14550``).
See docs/simulator.md.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import threading
from pathlib import Path
from typing import TYPE_CHECKING

os.environ.setdefault("MAVLINK20", "1")

from planner.errors import UserError  # noqa: E402
from planner.scenario import load_scenario  # noqa: E402
from sim_gateway.signing import load_or_create_key_file, load_signing_key  # noqa: E402
from sim_gateway.sim_options import RadioOptions  # noqa: E402
from swarmplan import option_groups  # noqa: E402
from swarmplan.arguments import (  # noqa: E402
    finite_float,
    km_point,
    non_negative_float,
    non_negative_int,
    port_number,
    positive_float,
)

if TYPE_CHECKING:
    from sim_gateway.simulator import Simulator
    from sim_gateway.target_account import TargetAccount

HELP = (
    "run N simulated fixed-wing autopilots (ArduPlane-like) over UDP MAVLink in front of the world"
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    option_groups.add_world_arguments(
        parser, "paper-10uav", "seed of the world and the random starts"
    )
    _add_pace_arguments(parser)
    _add_address_arguments(parser)
    _add_vehicle_start_arguments(parser)
    option_groups.add_duration_option(parser, "simulated")
    _add_lockstep_arguments(parser)
    add_radio_arguments(parser)
    option_groups.add_signing_key_option(
        parser,
        "sign everything, refuse unsigned or wrongly signed commands; a file that does not "
        "exist is created with a new key for this mission (mode 0600): give the daemon the same "
        "--signing-key-file",
        otherwise="unsigned",
    )
    option_groups.add_target_account_option(parser)
    option_groups.add_quiet_option(parser)


def _add_pace_arguments(parser: argparse.ArgumentParser) -> None:
    """How fast simulated time runs against the wall clock, and its physics tick."""
    parser.add_argument(
        "--speedup", type=positive_float, default=1.0, help="simulated seconds per wall second"
    )
    parser.add_argument(
        "--fast", action="store_true", help="run as fast as possible (deterministic ticks)"
    )
    parser.add_argument(
        "--tick-s", type=positive_float, default=0.1, help="physics tick, simulated s"
    )


def _add_address_arguments(parser: argparse.ArgumentParser) -> None:
    """Where the vehicles send to and receive on."""
    parser.add_argument(
        "--gcs-host", default="127.0.0.1", help="where vehicles send (ground station / daemon)"
    )
    parser.add_argument(
        "--gcs-port", type=port_number, default=14550, help="UDP port all vehicles send to"
    )
    parser.add_argument(
        "--truth-port",
        type=port_number,
        default=None,
        help="send the true targets, one JSON datagram per decision period, to 127.0.0.1:PORT "
        "(for a display: swarmplan demo's live view; never to the planner)",
    )
    parser.add_argument(
        "--per-vehicle-ports",
        type=port_number,
        default=None,
        metavar="BASE",
        help="vehicle i sends to BASE+i instead of --gcs-port (e.g. 14540, PX4 style)",
    )
    parser.add_argument(
        "--bind-host", default="127.0.0.1", help="local address of the vehicle sockets"
    )
    parser.add_argument(
        "--bind-base-port",
        type=port_number,
        default=0,
        metavar="BASE",
        help="vehicle i receives on BASE+i (default 0: any free port)",
    )


def _add_vehicle_start_arguments(parser: argparse.ArgumentParser) -> None:
    """Which UAVs, and how the vehicles start: their boot, in the air or not, their telemetry
    rate."""
    parser.add_argument(
        "--first-uav", type=non_negative_int, default=None, metavar="K",
        help="fly the scenario's UAVs from K (0-based) on, as system ids 1..; a swarm of more "
        "than 250 flies as several simulators on their own ports, the daemon told with "
        "--connect ENDPOINT@K (default: --vehicles makes a scenario of that many UAVs)",
    )  # fmt: skip
    parser.add_argument(
        "--boot-s", type=non_negative_float, default=20.0, help="simulated boot (pre-arm) phase, s"
    )
    parser.add_argument("--airborne", action="store_true", help="start armed and flying, in LOITER")
    parser.add_argument(
        "--telemetry-hz", type=positive_float, default=10.0, help="position/attitude rate (wall)"
    )


def _add_lockstep_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--lockstep",
        action="store_true",
        help="simulated time advances only as far as the ground station grants (SYSTEM_TIME); "
        "as fast as possible and deterministic for a seed (docs/simulator.md)",
    )
    parser.add_argument(
        "--lockstep-timeout",
        type=positive_float,
        default=10.0,
        help="wall s of ground-station silence after which lockstep is released (default 10)",
    )


def add_radio_arguments(parser: argparse.ArgumentParser) -> None:
    """The telemetry radio that carries the planner nodes' swarm link (docs/onboard.md)."""
    group = parser.add_argument_group(
        "swarm radio", "the link between the vehicles' planner nodes (TUNNEL frames of the swarm "
        "payload type); default: every vehicle hears every other at once, nothing lost"
    )  # fmt: skip
    group.add_argument(
        "--radio-range-km", type=finite_float, default=None, metavar="KM",
        help="a frame reaches only the vehicles within KM of its sender (default: unlimited)",
    )  # fmt: skip
    group.add_argument(
        "--radio-loss", type=finite_float, default=0.0, metavar="P",
        help="each receiver loses each frame with probability P in [0, 1] (seeded)",
    )  # fmt: skip
    group.add_argument(
        "--radio-latency-ms", type=finite_float, default=0.0, metavar="MS",
        help="simulated delay of every frame after it left the channel (default 0)",
    )  # fmt: skip
    group.add_argument(
        "--radio-kbps", type=finite_float, default=None, metavar="KBPS",
        help="the channel's rate shared by all vehicles, kbit/s (e.g. 57.6); a frame that "
        "would wait more than a decision period is dropped (default: unlimited)",
    )  # fmt: skip
    group.add_argument(
        "--radio-ground-port", type=port_number, default=None, metavar="PORT",
        help="a ground station listens on the channel: the frames it hears (same range, "
        "loss and latency, from its antenna) go to --gcs-host:PORT (swarmplan demo --onboard's "
        "coordinator); default: none",
    )  # fmt: skip
    group.add_argument(
        "--radio-ground-km", type=km_point, default=None, metavar="X,Y",
        help="where that ground station's antenna is, mission frame km (default: the area's "
        "centre)",
    )  # fmt: skip


def radio_options(args: argparse.Namespace) -> RadioOptions:
    """The radio of ``swarmplan sim``'s options (checked by the simulator)."""
    return RadioOptions(
        range_km=math.inf if args.radio_range_km is None else args.radio_range_km,
        loss=args.radio_loss,
        latency_ms=args.radio_latency_ms,
        kbps=math.inf if args.radio_kbps is None else args.radio_kbps,
    )


def main(args: argparse.Namespace) -> int:
    from sim_gateway.simulator import SimOptions, Simulator

    scenario = load_scenario(args.scenario)
    signing_key = simulator_key(args.signing_key_file)
    options = SimOptions(
        seed=args.seed,
        vehicles=args.vehicles,
        first_uav=args.first_uav,
        speedup=args.speedup,
        fast=args.fast,
        tick_s=args.tick_s,
        gcs_host=args.gcs_host,
        gcs_port=args.gcs_port,
        truth_port=args.truth_port,
        per_vehicle_port_base=args.per_vehicle_ports,
        bind_host=args.bind_host,
        bind_port_base=args.bind_base_port,
        boot_s=args.boot_s,
        airborne=args.airborne,
        position_rate_hz=args.telemetry_hz,
        signing_key=signing_key,
        lockstep=args.lockstep,
        lockstep_timeout_s=args.lockstep_timeout,
        radio=radio_options(args),
        radio_ground_port=args.radio_ground_port,
        radio_ground_km=args.radio_ground_km,
    )
    with Simulator(scenario, options) as sim:
        n = len(sim.vehicles)
        base = options.per_vehicle_port_base
        ports_out = f"{options.gcs_port}" if base is None else f"{base}..{base + n - 1}"
        dest = f"{options.gcs_host}:{ports_out}"
        ports = ",".join(str(s.local_port) for s in sim.sockets[:4]) + ("..." if n > 4 else "")
        pace = (
            "fast"
            if options.fast
            else "lockstep (waiting for the ground station's grants)"
            if options.lockstep
            else f"{options.speedup:g}x"
        )
        print(
            f"sim: {n} vehicles (sysid 1..{n}) of scenario {scenario.name!r}, "
            f"seed {options.seed}, {pace}; sending to udp {dest} "
            f"from {options.bind_host} ports {ports}",
            flush=True,
        )

        def progress(s: Simulator) -> None:
            if not args.quiet:
                print(
                    f"sim: t={s.sim_time_s:.0f}s step {s.decision_step} "
                    f"airborne {int(s.fleet.airborne.sum())}/{n} looks {s.looks_sent} "
                    f"engagements {s.engagements} bad datagrams {s.stats.bad_datagrams}",
                    flush=True,
                )

        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, _interrupt)
        with contextlib.suppress(KeyboardInterrupt):
            sim.run(sim_duration_s=args.duration_s, on_progress=progress)
        print(json.dumps(sim.summary()), flush=True)
        if args.target_account is not None:
            write_target_truth(sim.target_account, args.target_account)
    return 0


def simulator_key(path: Path | None) -> bytes | None:
    """The vehicles' signing key: from ``path``, made for this mission there when the file does
    not exist (said in one line), else ``$SWARMPLAN_SIGNING_KEY``, else None (unsigned)."""
    if path is None:
        return load_signing_key(None)
    key, made = load_or_create_key_file(path)
    if made:
        print(
            f"sim: made a signing key for this mission in {path} (mode 0600); fly with "
            f"`swarmplan daemon --signing-key-file {path}`",
            flush=True,
        )
    return key


def write_target_truth(account: TargetAccount, path: Path) -> None:
    """A simulator's ground-truth target account as JSON at ``path`` (written whole, then
    renamed into place, so a reader never sees half a file)."""
    partial = path.with_name(path.name + ".partial")
    try:
        partial.write_text(json.dumps(account.truth()))
        partial.replace(path)
    except OSError as exc:
        raise UserError(
            f"cannot write the target account to {path} ({exc.strerror}); choose another "
            "--target-account path"
        ) from None


def _interrupt(signum: int, frame: object) -> None:
    """SIGTERM ends the run like Ctrl-C: sockets closed, summary printed."""
    raise KeyboardInterrupt
