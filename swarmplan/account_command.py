"""``swarmplan account``: the per-target account of a daemon's mission, after the fact.

The daemon has no ground truth: its result.json keeps the planner's facts (``planner_facts``)
and each decision step's look time stamps (``look_times_ms``). A simulator run with
``--target-account PATH`` writes its truth there when it stops. This command joins the two
(``sim_gateway.target_account.account_of_ground_station``, the demo's own join) into the
result's ``target_account``, rewrites result.json and draws ``targets.png`` beside it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from planner.errors import UserError
from planner.scenario import load_scenario
from sim_gateway.target_account import account_of_ground_station, format_account

HELP = "join a simulator's ground truth to a daemon's result.json: the per-target account"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "run", type=Path, help="the daemon's --out folder (holding result.json), or result.json"
    )
    parser.add_argument(
        "--truth", type=Path, required=True,
        help="the simulator's ground truth (swarmplan sim --target-account PATH)",
    )  # fmt: skip


def read_json(path: Path, what: str, fix: str) -> dict:
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise UserError(f"cannot read {what} {path} ({exc.strerror}); {fix}") from None
    except ValueError as exc:
        raise UserError(f"{what} {path} is not JSON ({exc}); {fix}") from None
    if not isinstance(data, dict):
        raise UserError(f"{what} {path} is not a JSON object; {fix}")
    return data


def main(args: argparse.Namespace) -> int:
    result_path = args.run / "result.json" if args.run.is_dir() else args.run
    result = read_json(
        result_path, "the result", "give the daemon's --out folder or its result.json"
    )
    if "look_times_ms" not in result or "planner_facts" not in result:
        raise UserError(
            f"{result_path} is not a daemon's result with planner facts and look times (an "
            "offline run or experiment has its account already); fly it with swarmplan daemon"
        )
    truth = read_json(
        args.truth, "the truth", "give the file the simulator wrote with --target-account PATH"
    )
    if not {"targets", "steps", "times_ms", "positions_km"} <= set(truth):
        raise UserError(
            f"{args.truth} is not a simulator's target truth; give the file swarmplan sim "
            "wrote with --target-account PATH"
        )
    try:
        scenario = load_scenario(str(result["scenario"]))
    except (UserError, KeyError) as exc:
        raise UserError(
            f"cannot load the scenario of {result_path} ({exc}); run this where it was flown"
        ) from None
    ids = [t["id"] for t in truth["targets"]]
    if ids != [t.id for t in scenario.targets]:
        raise UserError(
            f"{args.truth} holds targets {ids}, not those of scenario {result['scenario']}; "
            "give the truth of the simulator this daemon flew with"
        )
    if not _matched(truth, result, scenario.config.step_s):
        raise UserError(
            f"no decision step of {result_path} matches a step of {args.truth} by the looks' "
            "time stamps; give the truth of the simulator this daemon flew with"
        )
    account = account_of_ground_station(truth, result, scenario.config.step_s)
    result["target_account"] = account
    try:
        result_path.write_text(json.dumps(result, indent=2, default=float))
    except OSError as exc:
        raise UserError(f"cannot write {result_path} ({exc.strerror})") from None
    from swarmplan.figures import plot_target_funnel

    figure = plot_target_funnel(result, result_path.parent / "targets.png")
    print(format_account(account))
    print(f"files in        {result_path.parent}/ (result.json with target_account, {figure.name})")
    return 0


def _matched(truth: dict, result: dict, step_s: float) -> bool:
    """Does some daemon step's look time lie within half a period of a truth step's?"""
    times = [t for t in truth["times_ms"] if t is not None]
    tolerance = 500.0 * step_s
    return any(
        abs(t - ms) <= tolerance for _, ms in result.get("look_times_ms") or [] for t in times
    )
