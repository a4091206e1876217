"""``swarmplan daemon``'s arguments, the options they make, the mission view around the flight,
and the progress and summary lines. The command itself (which also writes the figures, on every
way out) is composed one layer up, in ``swarmplan/daemon_command.py``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from mavlink_bridge.daemon import DaemonOptions, MissionDaemon, StepStatus
from mavlink_bridge.mission_result import lost_vehicle_lines
from mavlink_bridge.signing import KEY_ENV, load_signing_key, unsigned_warning
from mission_view.view_session import add_view_arguments
from planner.errors import UserError
from planner.metrics import format_summary
from swarmplan.arguments import (
    add_seed_argument,
    non_negative_float,
    positive_float,
    positive_int,
)

HELP = "fly MAVLink vehicles (SITL, hardware or the simulator) with the HAPF-ACO planner"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="udpin:HOST:PORT (shared by many vehicles), udpout:HOST:PORT or tcp:HOST:PORT "
        "(one per vehicle, e.g. ArduPilot SITL tcp:127.0.0.1:5760, 5770...); repeatable; "
        "default udpin:0.0.0.0:14550",
    )
    parser.add_argument("--scenario", default="paper-10uav", help="built-in name or TOML file")
    add_seed_argument(parser, "planner seed")
    parser.add_argument(
        "--expect",
        type=positive_int,
        help="vehicles to wait for: system ids 1..N (default: the scenario's UAV count)",
    )
    parser.add_argument(
        "--steps", type=positive_int, help="decision steps (default: the scenario's)"
    )
    parser.add_argument(
        "--timeout",
        type=positive_float,
        default=60.0,
        help="seconds to wait for every expected vehicle (default 60)",
    )
    parser.add_argument(
        "--ready-timeout",
        type=positive_float,
        default=120.0,
        help="wall seconds to wait until every vehicle can arm (pre-arm checks pass, GPS fix, "
        "home known), arming retried meanwhile; ArduPlane SITL needs ~20 s of its clock "
        "(default 120)",
    )
    parser.add_argument(
        "--lost-after",
        type=positive_float,
        default=3.0,
        help="wall seconds of silence before a vehicle counts as lost (wall time: a silent "
        "vehicle has no clock of its own; default 3)",
    )
    parser.add_argument(
        "--rtl-watch",
        type=non_negative_float,
        metavar="S",
        help="after the last step, watch the flight home for at most S of the vehicles' "
        "seconds (0: not at all; default: the farthest plane's flight home plus two minutes)",
    )
    parser.add_argument(
        "--threat-margin-km",
        type=non_negative_float,
        default=None,
        help="safety envelope clearance from threat circles (default: the airframe's loiter "
        "circle + 0.25 km, at most 1 km; ArduPlane's defaults: 0.33 km)",
    )
    parser.add_argument(
        "--time-scale",
        type=positive_float,
        default=1.0,
        help="speed of the vehicles' clock (SITL --speedup): the first steps' deadline until the "
        "daemon has measured it; steps follow the vehicles' own clock (default 1)",
    )
    parser.add_argument(
        "--checkpoint",
        type=Path,
        metavar="PATH",
        help="write the planner state here (atomically) after every step, to --resume from",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="carry on from --checkpoint (a restarted daemon); flying vehicles are not "
        "re-armed or taken off again",
    )
    parser.add_argument(
        "--signing-key-file",
        type=Path,
        metavar="PATH",
        help="MAVLink 2 signing key (64 hex characters or 32 bytes): sign everything sent, "
        f"refuse unsigned frames; default ${KEY_ENV} if set (never a command-line value), "
        "else unsigned (said at start); `swarmplan sim --signing-key-file PATH` makes one",
    )
    parser.add_argument(
        "--lockstep",
        action="store_true",
        help="the vehicles are `swarmplan sim --lockstep`: grant simulated time one decision "
        "step at a time (as fast as possible, repeatable for a seed)",
    )
    add_leg_timing_arguments(parser)
    parser.add_argument(
        "--airspeed-range",
        type=airspeed_range,
        metavar="MIN:MAX",
        help="slowest and fastest airspeed (m/s) the daemon asks for when timing legs; inside "
        "the airframe's AIRSPEED_MIN/AIRSPEED_MAX (default: the scenario's speed .. 1.5 x it)",
    )
    parser.add_argument("--tlog", type=Path, help="telemetry log (default OUT/mission.tlog)")
    parser.add_argument(
        "--out", type=Path, default=Path("out/daemon"), help="output folder (default out/daemon)"
    )
    add_view_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print only the result JSON")


def add_leg_timing_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--no-leg-timing",
        dest="leg_timing",
        action="store_false",
        help="fly every leg at the scenario's speed instead of timing each leg to one decision "
        "step with MAV_CMD_DO_CHANGE_SPEED (the paper's grid flies a diagonal cell, 1.41 km, "
        "per step; at constant speed the planes fall behind it)",
    )


def airspeed_range(text: str) -> tuple[float, float]:
    """``MIN:MAX`` in m/s, 0 < MIN <= MAX."""
    try:
        low, high = (float(part) for part in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected MIN:MAX in m/s, e.g. 100:150, got {text!r}"
        ) from None
    if not (0 < low <= high < float("inf")):
        raise argparse.ArgumentTypeError(f"need 0 < MIN <= MAX, got {text!r}")
    return low, high


def validate(args: argparse.Namespace) -> None:
    """What the argument types cannot check alone (each value is checked by its type)."""
    if args.resume and args.checkpoint is None:
        raise UserError("--resume needs --checkpoint PATH (the file to resume from)")


def warn_if_unsigned(daemon: MissionDaemon) -> None:
    """One line on stderr (also with --json) when the mission flies without MAVLink signing."""
    if daemon.options.signing_key is None:
        fix = "give --signing-key-file PATH with the vehicles' key"
        print(f"swarmplan daemon: warning: {unsigned_warning(fix)}", file=sys.stderr, flush=True)


def print_step(status: StepStatus) -> None:
    lost = f" lost {status.lost}" if status.lost else ""
    print(
        f"\rstep {status.step:>4}/{status.steps}  active {status.active:>2}  coverage "
        f"{status.coverage * 100:5.1f}%  engaged {status.engaged:>2} "
        f"(value {status.engaged_value:g})"
        f"{lost}   ",
        end="",
        file=sys.stderr,
        flush=True,
    )


def daemon_options(args: argparse.Namespace, out: Path) -> DaemonOptions:
    """The daemon's options from the command line (``validate`` first)."""
    quiet = args.json
    return DaemonOptions(
        connect=args.connect or ["udpin:0.0.0.0:14550"],
        seed=args.seed,
        expect=args.expect,
        steps=args.steps,
        discovery_timeout_s=args.timeout,
        ready_timeout_s=args.ready_timeout,
        lost_after_s=args.lost_after,
        threat_margin_km=args.threat_margin_km,
        time_scale=args.time_scale,
        lockstep=args.lockstep,
        leg_timing=args.leg_timing,
        airspeed_range_mps=args.airspeed_range,
        rtl_watch_s=args.rtl_watch,
        checkpoint_path=args.checkpoint,
        resume=args.resume,
        signing_key=load_signing_key(args.signing_key_file),
        tlog_path=args.tlog or out / "mission.tlog",
        progress=None
        if quiet
        else (lambda text: print(f"\n{text}" if text else "", file=sys.stderr)),
        on_step=None if quiet else print_step,
    )


def fly_with_view(daemon: MissionDaemon, args: argparse.Namespace, out: Path) -> Any:
    """Fly the mission with the mission view (docs/view.md): the replay written to ``out``
    and, unless ``--no-view``, the live view served (its URL said on stderr)."""
    from mavlink_bridge.view_feed import DaemonViewFeed
    from mission_view.view_session import ViewSession, view_options

    view = ViewSession(
        daemon.scenario, seed=args.seed, steps=daemon.steps, uav_count=daemon.n,
        source="mavlink", truth=False, out_dir=out, options=view_options(args),
        append=args.resume,
    )  # fmt: skip
    feed = DaemonViewFeed(daemon, view)
    said = daemon.options.progress
    daemon.options.step_listeners.append(feed.listener)

    def progress(text: str) -> None:
        if said is not None:
            said(text)
        feed.progress(text)

    daemon.options.progress = progress
    if view.url is not None:
        print(f"daemon: live view at {view.url}", file=sys.stderr, flush=True)
    try:
        return daemon.fly()
    finally:
        view.close()
        view.stop()


def print_summary(result: dict, out: Path, files: list[Path]) -> None:
    """The metrics a person reads first, the lost vehicles, how the mission ended, then where
    the files are."""
    if result.get("steps"):
        print(format_summary(result))
    for line in lost_vehicle_lines(result):
        print(line)
    ended = result.get("ended", "completed")
    if ended != "completed":
        print(f"ended           {ended} (in phase {result.get('ended_in_phase', '?')})")
    rtl = result.get("rtl_sent_to") or []
    print(f"RTL sent to     {', '.join(str(i) for i in rtl) if rtl else 'no vehicle'}")
    print(f"files in        {out}/ (result.json, mission.tlog; {len(files)} files written)")
