"""``swarmplan export RESULT_DIR``: waypoint files (QGC WPL 110, QGroundControl .plan) and maps
(GeoJSON, KML) from the result.json of a run, demo or daemon mission."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mavlink_bridge.export.waypoint_export import FORMATS, export
from planner.errors import UserError
from swarmplan import option_groups

HELP = "write waypoint files (QGC WPL, QGroundControl .plan) and maps (GeoJSON, KML) of a result"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "result", type=Path, help="result folder (with result.json) or the JSON file"
    )
    parser.add_argument(
        "--format",
        action="append",
        choices=FORMATS,
        help="format to write (repeatable; default all)",
    )
    option_groups.add_out_option(parser, "the result folder")


def load_result(path: Path) -> dict:
    """The result dict in ``path`` (a folder holding result.json, or the file itself)."""
    file = path / "result.json" if path.is_dir() else path
    if not file.exists():
        raise UserError(
            f"{file} does not exist; give the output folder of `swarmplan run/demo/daemon`"
        )
    try:
        return json.loads(file.read_text())
    except json.JSONDecodeError as exc:
        raise UserError(
            f"{file} is not valid JSON ({exc.msg} at line {exc.lineno}); re-run the mission"
        ) from None


def main(args: argparse.Namespace) -> int:
    result = load_result(args.result)
    out = args.out or (args.result if args.result.is_dir() else args.result.parent)
    for path in export(result, out, args.format or FORMATS):
        print(path)
    return 0
