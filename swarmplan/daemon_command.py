"""``swarmplan daemon``: fly a swarm of MAVLink vehicles (SITL, hardware or ``swarmplan sim``)
with the HAPF-ACO planner; writes result.json, the figures (paths.png, coverage.png), the
waypoint files and the .tlog to --out, on every way out: the end, an error, Ctrl-C or SIGTERM
(after RTL to every airborne vehicle; docs/daemon.md, "A mission, phase by phase", 8).

This layer composes the daemon (``mavlink_bridge``) with the figures (``swarmplan.figures``), so
the dependencies point one way: swarmplan -> mavlink_bridge -> planner.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mavlink_bridge.cli import (
    HELP,
    add_arguments,
    daemon_options,
    fly_with_view,
    print_summary,
    validate,
    warn_if_unsigned,
)
from mavlink_bridge.daemon import MissionDaemon, MissionInterrupted
from planner.errors import UserError
from planner.scenario import load_scenario
from swarmplan.arguments import writable_folder
from swarmplan.interrupts import MissionSignals
from swarmplan.run_command import write_outputs

__all__ = ["HELP", "add_arguments", "main", "write_mission_outputs"]


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
