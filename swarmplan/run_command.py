"""``swarmplan run``: fly a scenario offline (world + planner in-process) and write its result."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tqdm import tqdm

from mission_view.replay_file import replay_path
from planner.errors import UserError
from planner.metrics import format_summary
from planner.registry import planner_names
from planner.scenario import load_scenario
from sim_gateway.offline_runner import run_offline
from sim_gateway.target_account import format_account
from swarmplan import option_groups
from swarmplan.arguments import planner_name, writable_folder

HELP = "fly a scenario offline (no MAVLink) and write result.json and figures"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    option_groups.add_scenario_argument(parser, positional=True)
    option_groups.add_seed_argument(parser, "random seed of the run")
    option_groups.add_steps_option(parser)
    parser.add_argument(
        "--algorithm",
        type=planner_name,
        default="hapf-aco",
        help=f"planner to fly: {', '.join(planner_names())} (default hapf-aco; "
        "docs/architecture.md says how to register one of your own)",
    )
    option_groups.add_out_option(parser, "runs/<scenario>-seed<S>")
    parser.add_argument(
        "--as-flown",
        action="store_true",
        help="plan with the margins the daemon flies the simulator's planes with (separation, "
        "threat clearance, home reserve: the offline run a 'swarmplan demo' is measured against)",
    )
    option_groups.add_json_option(parser)


def write_outputs(result: dict, out_dir: Path) -> list[Path]:
    """result.json, the figures and the waypoint files of a run, in ``out_dir``."""
    from swarmplan.figures import write_figures

    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        path = out_dir / "result.json"
        path.write_text(json.dumps(result, indent=1))
    except OSError as exc:
        raise UserError(
            f"cannot write to {out_dir} ({exc.strerror}); choose another --out folder"
        ) from None
    written = [path, *write_figures(result, out_dir)]
    try:
        from mavlink_bridge.export.waypoint_export import export_all
    except ImportError:
        return written
    return written + list(export_all(result, out_dir))


class ReplayRecording:
    """The replay of an offline run (``mission_view``; ``swarmplan view OUT`` shows it)."""

    def __init__(self, scenario, seed: int, steps: int, out_dir: Path) -> None:
        from mission_view.sources import OfflineViews
        from mission_view.view_session import ViewSession

        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(
                f"cannot write to {out_dir} ({exc.strerror}); choose another --out folder"
            ) from None
        self.views = OfflineViews(scenario)
        self.session = ViewSession(
            scenario, seed=seed, steps=steps, uav_count=scenario.uav_count, source="offline",
            truth=True, out_dir=out_dir, live=False,
        )  # fmt: skip

    def observe(self, record) -> None:
        self.session.post(self.views.view(record), record.planner)

    def close(self) -> None:
        self.session.close()


def record_replay(scenario, seed: int, steps: int, out_dir: Path) -> ReplayRecording:
    return ReplayRecording(scenario, seed, steps, out_dir)


def progress_bar(total: int, desc: str, quiet: bool) -> tqdm:
    """A progress bar on stderr when stderr is a terminal; nothing when it is a pipe or a file
    (tqdm's ``disable=None``: no ``\r`` redraws in logs) or with ``quiet`` (``--json``)."""
    return tqdm(
        total=total,
        desc=desc,
        unit="step",
        disable=True if quiet else None,
        file=sys.stderr,
        leave=False,
    )


def written_line(out: Path, files: list[Path]) -> str:
    """One line for the files a command wrote into ``out``: the folder, each file or subfolder
    directly in it once, and how many files there are."""
    names: list[str] = []
    for file in files:
        try:
            parts = Path(file).relative_to(out).parts
        except ValueError:  # written elsewhere (an explicit path)
            parts = (str(file),)
        name = parts[0] + ("/" if len(parts) > 1 else "")
        if name not in names:
            names.append(name)
    return f"written: {out}/ ({', '.join(names)}; {len(files)} files)"


def main(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    steps = args.steps or scenario.steps
    planning = None
    if args.as_flown:
        from swarmplan.as_flown import simulator_planning_scenario

        planning = simulator_planning_scenario(scenario, steps)
    out_dir = writable_folder(args.out or Path("runs") / f"{scenario.name}-seed{args.seed}")
    recording = record_replay(scenario, args.seed, steps, out_dir)
    with progress_bar(steps, f"{scenario.name} seed {args.seed}", args.json) as bar:
        try:
            result = run_offline(
                scenario, args.seed, steps, args.algorithm, progress=lambda k: bar.update(1),
                observer=recording.observe, planning=planning,
            )  # fmt: skip
        finally:
            recording.close()
    written = write_outputs(result, out_dir)
    if args.json:
        print(json.dumps(result))
    else:
        print(format_summary(result))
        if result.get("target_account"):
            print(format_account(result["target_account"]))
        replay = replay_path(out_dir)
        print(written_line(out_dir, [*written, *([replay] if replay.exists() else [])]))
    return 0
