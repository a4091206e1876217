"""``swarmplan experiment efficiency|swarm``: reproduce the paper's section 4 in one command.

Flies every (algorithm, scenario, seed) of the experiment in parallel (local processes, or a
Dask cluster with ``--dask``), then writes into ``--out``: each run's result JSON, ``runs.csv``,
``summary.csv``, ``friedman.csv``, the paper's figures and ``report.md`` (docs/experiments.md).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import time
from pathlib import Path

from planner.errors import UserError
from planner.registry import planner_factory
from swarmplan import option_groups
from swarmplan.arguments import positive_int, seed_int, writable_folder
from swarmplan.experiment_runner import ALGORITHMS, EXPERIMENTS, RunTask, execute, plan_tasks

HELP = "reproduce an experiment of the paper (all algorithms, many seeds): CSV, figures, report"

#: Dask scheduler addresses look like tcp://HOST:PORT (also tls://, ucx://, ws://, inproc://).
DASK_ADDRESS = re.compile(r"^(tcp|tls|ucx|ws|wss|inproc)://\S+$")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "experiment", help=f"which experiment: {' or '.join(EXPERIMENTS)} (paper sections 4.2, 4.3)"
    )
    parser.add_argument(
        "--runs",
        type=positive_int,
        default=30,
        help="seeds per algorithm and scenario (default 30)",
    )
    option_groups.add_out_option(parser, "runs/experiment-EXPERIMENT")
    parser.add_argument(
        "--jobs",
        type=positive_int,
        default=None,
        help="local worker processes (default: one per CPU)",
    )
    parser.add_argument(
        "--dask",
        default=None,
        metavar="tcp://HOST:PORT",
        help="run on this Dask distributed scheduler instead of local processes",
    )
    parser.add_argument(
        "--seed-base",
        type=seed_int,
        default=1,
        help="first seed; runs use seeds S .. S+runs-1 (default 1)",
    )
    parser.add_argument(
        "--steps",
        type=positive_int,
        default=None,
        help="decision steps per run (default: the scenario's, 250)",
    )
    parser.add_argument(
        "--algorithms",
        default=",".join(ALGORITHMS),
        help=f"comma-separated subset of {','.join(ALGORITHMS)} (default all)",
    )
    option_groups.add_quiet_option(parser, "progress bar")


def parse_options(args: argparse.Namespace) -> dict:
    """Check every option; a UserError names the first bad one and the fix."""
    if args.experiment not in EXPERIMENTS:
        raise UserError(
            f"unknown experiment {args.experiment!r}; choose {' or '.join(EXPERIMENTS)}"
        )
    algorithms = [a.strip() for a in str(args.algorithms).split(",") if a.strip()]
    if not algorithms:
        raise UserError("--algorithms names no algorithm; give a comma-separated list")
    for algorithm in algorithms:
        planner_factory(algorithm)  # one line naming an unknown or broken one
    if len(set(algorithms)) != len(algorithms):
        raise UserError(f"--algorithms lists an algorithm twice: {args.algorithms}")
    if args.dask is not None and args.jobs is not None:
        raise UserError("give either --jobs (local processes) or --dask (a cluster), not both")
    if args.dask is not None and not DASK_ADDRESS.match(args.dask):
        raise UserError(f"--dask {args.dask!r} is not a scheduler address; give tcp://HOST:PORT")
    out = args.out or Path("runs") / f"experiment-{args.experiment}"
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} is a file, not a folder; choose another --out")
    return {
        "experiment": args.experiment,
        "runs": args.runs,
        "jobs": args.jobs or os.cpu_count() or 1,
        "seed_base": args.seed_base,
        "steps": args.steps,
        "algorithms": algorithms,
        "dask": args.dask,
        "out": out,
        "progress": not args.quiet,
    }


def _command_line(opts: dict) -> str:
    parts = [
        "swarmplan",
        "experiment",
        opts["experiment"],
        "--runs",
        str(opts["runs"]),
        "--out",
        str(opts["out"]),
    ]
    parts += ["--dask", opts["dask"]] if opts["dask"] else ["--jobs", str(opts["jobs"])]
    parts += ["--seed-base", str(opts["seed_base"])]
    if opts["steps"] is not None:
        parts += ["--steps", str(opts["steps"])]
    if tuple(opts["algorithms"]) != ALGORITHMS:
        parts += ["--algorithms", ",".join(opts["algorithms"])]
    return shlex.join(parts)


def _slim(result: dict) -> dict:
    """A result without the UAV tracks (kept only for the runs whose paths are drawn)."""
    slim = dict(result)
    slim["uavs"] = [
        {k: v for k, v in u.items() if k not in ("track_km", "planned_km")} for u in result["uavs"]
    ]
    return slim


def run_experiment(opts: dict) -> dict:
    """Run, write every output, and return a summary (paths and wall time)."""
    from swarmplan.experiment_figures import write_experiment_figures
    from swarmplan.experiment_stats import friedman_csv, report_markdown, runs_csv, summary_csv

    out: Path = writable_folder(opts["out"])
    tasks = plan_tasks(
        opts["experiment"], opts["runs"], opts["seed_base"], opts["steps"], opts["algorithms"]
    )

    def keep(task: RunTask, result: dict) -> None:
        folder = out / "runs" / task.scenario.name / task.algorithm
        try:
            folder.mkdir(parents=True, exist_ok=True)
            (folder / f"seed-{task.seed:04d}.json").write_text(
                json.dumps(result, separators=(",", ":"))
            )
        except OSError as exc:
            raise UserError(
                f"cannot write to {folder} ({exc.strerror}); choose another --out"
            ) from None

    load_before = os.getloadavg()
    started = time.perf_counter()
    by_key = execute(tasks, opts["jobs"], opts["dask"], opts["progress"], on_result=keep)
    wall = time.perf_counter() - started
    load_after = os.getloadavg()
    results = [_slim(by_key[t.key]) for t in tasks]
    # the paths are drawn for the first seed of each (scenario, algorithm), in canonical order
    path_runs = [by_key[t.key] for t in tasks if t.seed == opts["seed_base"]]

    files = {
        "runs.csv": runs_csv(results),
        "summary.csv": summary_csv(results),
        "friedman.csv": friedman_csv(results),
    }
    for name, text in files.items():
        (out / name).write_text(text)
    figures = write_experiment_figures(opts["experiment"], results, path_runs, out / "figures")
    processes = f"{opts['jobs']} local process{'es' if opts['jobs'] > 1 else ''}"
    where = f"the Dask cluster at {opts['dask']}" if opts["dask"] else processes
    where += f" (this machine: {os.cpu_count()} CPUs)"
    report = report_markdown(
        opts["experiment"],
        results,
        command=_command_line(opts),
        wall_time_s=wall,
        where=where,
        load_before=load_before,
        load_after=load_after,
        figures=[str(p.relative_to(out)) for p in figures],
    )
    (out / "report.md").write_text(report)
    return {"out": out, "runs": len(results), "wall_time_s": wall, "figures": figures}


def main(args: argparse.Namespace) -> int:
    opts = parse_options(args)
    summary = run_experiment(opts)
    out = summary["out"]
    print(f"{opts['experiment']}: {summary['runs']} runs in {summary['wall_time_s']:.1f} s")
    tables = ", ".join(
        str(out / name) for name in ("report.md", "runs.csv", "summary.csv", "friedman.csv")
    )
    print(
        f"written: {tables}, {len(summary['figures'])} figures in {out / 'figures'}, "
        f"per-run JSON in {out / 'runs'}"
    )
    return 0
