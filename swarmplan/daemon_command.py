"""``swarmplan daemon``: fly a swarm of MAVLink vehicles (SITL, hardware or ``swarmplan sim``)
with the HAPF-ACO planner; writes result.json, the figures (paths.png, coverage.png), the
waypoint files and the .tlog to --out, on every way out: the end, an error, Ctrl-C or SIGTERM
(after RTL to every airborne vehicle; docs/daemon.md, "A mission, phase by phase", 8).

The command's arguments and the options they make, the mission view around the flight, the
progress and summary lines. This layer composes the daemon (``mavlink_bridge``) with the
figures (``swarmplan.figures``), so the dependencies point one way:
swarmplan -> mavlink_bridge -> planner.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from mavlink_bridge.mission.daemon import (
    DaemonOptions,
    MissionDaemon,
    MissionInterrupted,
    StepStatus,
)
from mavlink_bridge.results.mission_result import lost_vehicle_lines
from mavlink_wire.signing import load_signing_key, unsigned_warning
from planner.errors import UserError
from planner.metrics import format_summary
from planner.scenario import load_scenario
from swarmplan import option_groups
from swarmplan.arguments import (
    non_negative_float,
    positive_float,
    positive_int,
    writable_folder,
)
from swarmplan.interrupts import MissionSignals
from swarmplan.run_command import write_outputs

HELP = "fly MAVLink vehicles (SITL, hardware or the simulator) with the HAPF-ACO planner"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="udpin:HOST:PORT (shared by many vehicles), udpout:HOST:PORT or tcp:HOST:PORT "
        "(one per vehicle, e.g. ArduPilot SITL tcp:127.0.0.1:5760, 5770...); repeatable; "
        "ENDPOINT@K: a MAVLink network of its own whose system id s is the scenario's UAV "
        "K + s - 1 (swarmplan sim --first-uav K; more than 250 vehicles); "
        "default udpin:0.0.0.0:14550",
    )
    option_groups.add_scenario_argument(parser, "paper-10uav")
    option_groups.add_seed_argument(parser, "planner seed")
    parser.add_argument(
        "--expect",
        type=positive_int,
        help="vehicles to wait for: system ids 1..N (default: the scenario's UAV count)",
    )
    option_groups.add_steps_option(parser)
    _add_wait_arguments(parser)
    _add_flight_arguments(parser)
    _add_restart_arguments(parser)
    option_groups.add_signing_key_option(
        parser,
        "sign everything sent, refuse unsigned frames; `swarmplan sim --signing-key-file PATH` "
        "makes one",
        otherwise="unsigned (said at start)",
    )
    parser.add_argument(
        "--lockstep",
        action="store_true",
        help="the vehicles are `swarmplan sim --lockstep`: grant simulated time one decision "
        "step at a time (as fast as possible, repeatable for a seed)",
    )
    option_groups.add_leg_timing_option(parser)
    parser.add_argument(
        "--airspeed-range",
        type=airspeed_range,
        metavar="MIN:MAX",
        help="slowest and fastest airspeed (m/s) the daemon asks for when timing legs; inside "
        "the airframe's AIRSPEED_MIN/AIRSPEED_MAX (default: the scenario's speed .. 1.5 x it)",
    )
    parser.add_argument("--tlog", type=Path, help="telemetry log (default OUT/mission.tlog)")
    option_groups.add_out_option(parser, "out/daemon", default=Path("out/daemon"))
    option_groups.add_view_options(parser)
    option_groups.add_json_option(parser)


def _add_wait_arguments(parser: argparse.ArgumentParser) -> None:
    """How long the daemon waits for the vehicles: to be heard, to be ready, before one is lost."""
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


def _add_flight_arguments(parser: argparse.ArgumentParser) -> None:
    """The flight home, the clearance from threats and the vehicles' clock."""
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


def _add_restart_arguments(parser: argparse.ArgumentParser) -> None:
    """A checkpoint after every step, and a restarted daemon carrying on from it."""
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
    from mavlink_bridge.mission.view_feed import DaemonViewFeed
    from mission_view.view_session import ViewSession

    view = ViewSession(
        daemon.scenario, seed=args.seed, steps=daemon.steps, uav_count=daemon.n,
        source="mavlink", truth=False, out_dir=out, options=option_groups.view_options(args),
        append=args.resume, actions=daemon.operator.inbox,
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


def write_mission_outputs(result: dict, out: Path) -> list[Path]:
    """result.json always; the figures and waypoint files too once a step was flown."""
    if result.get("steps"):
        return write_outputs(result, out)
    try:
        path = out / "result.json"
        path.write_text(json.dumps(result, indent=1, default=float))
    except OSError as exc:
        raise UserError(f"cannot write to {out} ({exc.strerror}); choose another --out") from None
    return [path]


def main(args: argparse.Namespace) -> int:
    validate(args)
    scenario = load_scenario(args.scenario)
    out: Path = writable_folder(args.out)
    daemon = MissionDaemon(scenario, daemon_options(args, out))
    daemon.prepare()  # a bad checkpoint, time scale or endpoint: one line, before the view
    warn_if_unsigned(daemon)
    with MissionSignals() as signals:
        try:
            fly_with_view(daemon, args, out)
        except MissionInterrupted:
            if daemon.report is None:
                raise  # before anything was flown: nothing to write
            # else: written and said below
        finally:
            report = daemon.report
            files = [] if report is None else write_mission_outputs(report.result, out)
    assert report is not None
    result = report.result
    if args.json:
        print(json.dumps(result, default=float))
    else:
        print(file=sys.stderr)
        print_summary(result, out, files)
    if signals.received is not None:
        print(f"swarmplan daemon: interrupted ({signals.received})", file=sys.stderr)
        return signals.exit_status
    return 0
