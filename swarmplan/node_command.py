"""``swarmplan node``: the planner of ONE UAV, run beside its autopilot (a companion computer's
place; docs/onboard.md). It is the daemon for a fleet of one vehicle: it launches its own
vehicle (fence, arm, take off) under the daemon's safety rules, plans only its own UAV with its
own beliefs (``mavlink_bridge/mission/onboard_planner.py``), hears its neighbours over the swarm
link (TUNNEL frames its autopilot or the simulator's radio carries), commands only its own
autopilot, flies home by the mission's end and writes its own part of the result
(``OUT/result.json``: ``architecture`` onboard, ``uav``, ``link``). It never needs a ground
station."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from mavlink_bridge.mission.daemon import DaemonOptions, MissionDaemon, MissionInterrupted
from mavlink_bridge.mission.onboard_planner import OnboardPlanner
from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_wire.protocol import GCS_COMPONENT_ID, GCS_SYSTEM_ID
from mavlink_wire.signing import load_signing_key, unsigned_warning
from planner.errors import UserError
from planner.scenario import load_scenario
from swarmplan import option_groups
from swarmplan.arguments import positive_float, system_id, uav_index, writable_folder
from swarmplan.daemon_command import validate, write_mission_outputs
from swarmplan.interrupts import MissionSignals

HELP = "the planner of one UAV beside its autopilot (onboard, no ground station needed)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    option_groups.add_scenario_argument(parser, positional=True)
    parser.add_argument(
        "--connect",
        action="append",
        required=True,
        metavar="ENDPOINT",
        help="its autopilot: udpin:HOST:PORT, udpout:HOST:PORT or tcp:HOST:PORT (e.g. a spare "
        "serial port of ArduPilot SITL, or `swarmplan sim --per-vehicle-ports BASE`: "
        "udpin:127.0.0.1:BASE+I)",
    )
    parser.add_argument(
        "--uav",
        type=uav_index,
        required=True,
        metavar="I",
        help="the scenario's UAV this node plans (0-based; its autopilot is system id I+1)",
    )
    parser.add_argument(
        "--system-id",
        type=system_id,
        default=GCS_SYSTEM_ID,
        metavar="N",
        help="its own MAVLink system id (component 190), the one its autopilot's MAV_GCS_SYSID "
        "(SYSID_MYGCS before ArduPilot 4.7) names, so that only its own heartbeat keeps the "
        f"plane's GCS failsafe quiet (default {GCS_SYSTEM_ID}, a ground station's; "
        'docs/onboard.md, "On a companion computer")',
    )
    option_groups.add_seed_argument(parser, "planner seed (the same for every node of a swarm)")
    option_groups.add_steps_option(parser)
    option_groups.add_signing_key_option(
        parser, "sign everything sent, refuse unsigned frames", otherwise="unsigned (said at start)"
    )
    parser.add_argument(
        "--time-scale",
        type=positive_float,
        default=1.0,
        help="speed of the vehicles' clock (SITL or simulator --speedup; default 1)",
    )
    parser.add_argument(
        "--timeout",
        type=positive_float,
        default=60.0,
        help="seconds to wait for its vehicle to be heard (default 60)",
    )
    option_groups.add_leg_timing_option(parser)
    parser.add_argument(
        "--checkpoint",
        type=Path,
        metavar="PATH",
        help="write this node's state (its UAV's beliefs, what it heard, the loop, the result so "
        "far) here atomically after every step, to --resume from",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="carry on from --checkpoint (a restarted companion computer): take the plane back, "
        "rejoin the swarm at its current step, plan on and bring the plane home by the end",
    )
    option_groups.add_out_option(parser, "runs/<scenario>-seed<S>-node-<I>")
    option_groups.add_json_option(parser)


def node_options(args: argparse.Namespace, out: Path, quiet: bool) -> DaemonOptions:
    prefix = f"node {args.uav}: "
    return DaemonOptions(
        connect=args.connect,
        seed=args.seed,
        fleet=(args.uav,),
        steps=args.steps,
        discovery_timeout_s=args.timeout,
        time_scale=args.time_scale,
        leg_timing=args.leg_timing,
        signing_key=load_signing_key(args.signing_key_file),
        source=(args.system_id, GCS_COMPONENT_ID),
        tlog_path=out / "mission.tlog",
        checkpoint_path=args.checkpoint,
        resume=args.resume,
        checkpoint_role=f"node {args.uav}",
        # the node's step is measured as it flies (link figures), not calibrated for a swarm
        check_time_scale=False,
        progress=None if quiet else (lambda text: print(prefix + text, file=sys.stderr)),
        on_step=None
        if quiet
        else (
            lambda s: print(
                f"{prefix}step {s.step:>4}/{s.steps}  coverage {s.coverage * 100:5.1f}%  "
                f"engaged {s.engaged}",
                file=sys.stderr,
                flush=True,
            )
        ),
    )


def main(args: argparse.Namespace) -> int:
    validate(args)
    scenario = load_scenario(args.scenario)
    if args.uav >= scenario.uav_count:
        raise UserError(
            f"--uav {args.uav} is not a UAV of {scenario.name} (0..{scenario.uav_count - 1})"
        )
    out: Path = writable_folder(
        args.out or Path("runs") / f"{scenario.name}-seed{args.seed}-node-{args.uav}"
    )
    daemon = MissionDaemon(scenario, node_options(args, out, args.json))
    period = scenario.config.step_s / max(args.time_scale, 1e-6)

    def factory(link: SwarmLink | None):
        def build(planning, starts, seed):
            say = daemon.options.progress or (lambda text: None)
            return OnboardPlanner(planning, starts, seed, uav=args.uav, link=link,
                                  period_wall_s=lambda: period, say=say)  # fmt: skip

        return build

    daemon.planner_factory = factory
    daemon.prepare()
    if daemon.options.signing_key is None:
        fix = "give --signing-key-file PATH with the swarm's key"
        print(f"swarmplan node: warning: {unsigned_warning(fix)}", file=sys.stderr, flush=True)
    with MissionSignals():
        try:
            daemon.fly()
        except MissionInterrupted:
            if daemon.report is None:
                raise
        finally:
            report = daemon.report
            if report is not None:
                result = report.result
                result["architecture"] = "onboard"
                result["uav"] = args.uav
                state = daemon.loop.state
                if state is not None:  # the cells its looks covered (the swarm's union: joined)
                    result["link"] = state.planner.link_summary()
                    result["observed_cells"] = np.flatnonzero(state.observed).tolist()
                write_mission_outputs(result, out)
    assert report is not None
    if args.json:
        print(json.dumps(report.result, default=float))
    else:
        link = report.result.get("link", {})
        sent = link.get("bytes_sent_per_step", {})
        resumed = report.result.get("resumed_from_step")
        missed = (
            ""
            if resumed is None
            else f" (resumed after step {resumed}; {link.get('steps_missed', 0)} steps missed)"
        )
        print(
            f"node {args.uav}: {report.result.get('ended', 'completed')}; "
            f"{report.result.get('steps', 0)} steps{missed}; sent {sent.get('mean', 0)} B/step "
            f"(max {sent.get('max', 0)}); files in {out}/"
        )
    return 0
