"""``swarmplan demo``: the whole system on one machine. Starts the MAVLink simulator (a
subprocess, ``swarmplan sim``) and the planner daemon on loopback UDP, flies the mission with a
progress bar, and prints the metrics measured over MAVLink (positions from telemetry, engagements
from their acknowledged outcomes) plus where the result, figures, waypoint files and .tlog are.

Both ends sign (MAVLink 2) with a key made for the mission unless told otherwise (``--no-signing``,
or a key given with ``--signing-key-file`` / ``$SWARMPLAN_SIGNING_KEY``). The simulator gets the
key in its environment (``$SWARMPLAN_SIGNING_KEY``): never on its command line, which ``ps``
shows every user, and never in a file, which would be left in the run folder users share or in a
temporary folder after a kill; a process's environment is readable by its own user only, as a
0600 file would be. The daemon runs in this process and takes the key directly. Nothing written
(result.json, replay, .tlog, sim.log) holds the key; result.json's ``signing`` says it was on.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from mavlink_bridge.cli import add_leg_timing_arguments
from mavlink_bridge.daemon import DaemonOptions, MissionDaemon, MissionInterrupted, StepStatus
from mavlink_bridge.discovery import DiscoveryError
from mavlink_bridge.mission_result import lost_vehicle_lines
from mavlink_bridge.signing import (
    KEY_ENV,
    key_environment,
    load_signing_key,
    mission_key,
    unsigned_warning,
)
from mavlink_bridge.vehicle_loss import paced_lost_after_s
from mavlink_bridge.view_feed import DaemonViewFeed
from mission_view.replay_file import replay_path
from mission_view.truth_receiver import TruthReceiver
from mission_view.view_session import ViewSession, add_view_arguments, view_options
from planner.errors import UserError
from planner.metrics import format_summary
from planner.scenario import BUILTIN_SCENARIOS, load_scenario
from sim_gateway.target_account import account_of_ground_station, format_account
from swarmplan.arguments import (
    add_seed_argument,
    positive_float,
    positive_int,
    writable_folder,
)
from swarmplan.daemon_command import write_mission_outputs
from swarmplan.interrupts import MissionSignals
from swarmplan.run_command import progress_bar, written_line

HELP = "fly a scenario end to end: the MAVLink simulator and the planner daemon on loopback UDP"

#: By default the simulator runs in lockstep with the daemon (``swarmplan sim --lockstep``): as
#: fast as both can go, and the same seed gives the same flight and result. ``--speedup X`` paces
#: it at X simulated seconds per wall second instead (what a SITL run looks like; not repeatable).
#: After the mission (RTL) a lockstep simulator runs on at this speed until it is stopped.
RELEASED_SPEEDUP = 100.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "scenario",
        nargs="?",
        default="paper-10uav",
        help=f"built-in ({', '.join(BUILTIN_SCENARIOS)}) or a TOML file (default paper-10uav)",
    )
    add_seed_argument(parser, "seed of the world and the planner")
    parser.add_argument(
        "--steps", type=positive_int, default=None, help="decision steps (default: the scenario's)"
    )
    parser.add_argument(
        "--speedup",
        type=positive_float,
        default=None,
        help="pace the simulator at this many simulated seconds per wall second instead of "
        "lockstep (default: lockstep, as fast as possible and repeatable for a seed)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder (default runs/<scenario>-seed<S>-demo)",
    )
    add_leg_timing_arguments(parser)
    signing = parser.add_mutually_exclusive_group()
    signing.add_argument(
        "--no-signing",
        action="store_true",
        help="fly without MAVLink 2 signing (default: the simulator and the daemon sign with a "
        "key made for this mission, kept in memory only)",
    )
    signing.add_argument(
        "--signing-key-file",
        type=Path,
        metavar="PATH",
        help=f"sign with this key (64 hex characters or 32 bytes) instead; ${KEY_ENV} if set",
    )
    add_view_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print only the result JSON on stdout")


def demo_key(args: argparse.Namespace) -> bytes | None:
    """The mission's signing key: None with ``--no-signing``, else the one given (a file or the
    environment), else a new one."""
    if args.no_signing:
        return None
    return load_signing_key(args.signing_key_file) or mission_key()


def start_simulator(
    scenario: str, seed: int, speedup: float | None, port: int, log: Path,
    target_truth: Path | None = None, truth_port: int | None = None,
    signing_key: bytes | None = None,
) -> subprocess.Popen:  # fmt: skip
    """``python -m swarmplan sim`` sending to our port (``--lockstep`` when ``speedup`` is
    None); its output goes to ``log``, its ground-truth target account to ``target_truth``, its
    true targets for the live view to UDP ``truth_port``; signing with ``signing_key`` (handed
    over in its environment), unsigned when None."""
    pace = ["--lockstep", "--speedup", f"{RELEASED_SPEEDUP:g}"]
    if speedup is not None:
        pace = ["--speedup", f"{speedup:g}"]
    command = [
        sys.executable,
        "-m",
        "swarmplan",
        "sim",
        "--scenario",
        scenario,
        "--seed",
        str(seed),
        *pace,
        "--gcs-host",
        "127.0.0.1",
        "--gcs-port",
        str(port),
        "--quiet",
        *([] if target_truth is None else ["--target-account", str(target_truth)]),
        *([] if truth_port is None else ["--truth-port", str(truth_port)]),
    ]
    with open(log, "wb") as sink:
        return subprocess.Popen(
            command, stdout=sink, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env=key_environment(signing_key),
        )  # fmt: skip


def stop_simulator(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def last_line(path: Path) -> str:
    try:
        lines = [line for line in path.read_text(errors="replace").splitlines() if line.strip()]
    except OSError:
        return ""
    return lines[-1] if lines else ""


def join_target_account(
    result: dict, truth_path: Path, step_s: float, say: Callable[[str], None]
) -> None:
    """The per-target account of a demo: the simulator's ground truth (``truth_path``, written
    when it stopped) joined with the daemon's result (``account_of_ground_station``)."""
    try:
        truth = json.loads(truth_path.read_text())
    except (OSError, ValueError) as exc:
        say(f"warning: no target account: the simulator's truth is unreadable ({exc})")
        return
    result["target_account"] = account_of_ground_station(truth, result, step_s)


def simulator_summary(path: Path) -> dict | None:
    """The simulator's JSON summary (the last JSON line of its log), if it wrote one."""
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        if line.startswith("{"):
            try:
                return json.loads(line)
            except ValueError:
                return None
    return None


def main(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    steps = args.steps or scenario.steps
    out = writable_folder(args.out or Path("runs") / f"{scenario.name}-seed{args.seed}-demo")
    quiet = args.json
    bar = progress_bar(steps, f"{scenario.name} over MAVLink", quiet)

    def on_step(status: StepStatus) -> None:
        if status.step > 0:  # step 0 is the start: the bar counts decision steps
            bar.update(1)
        bar.set_postfix_str(
            f"coverage {status.coverage * 100:.1f}% engaged {status.engaged} active {status.active}"
        )

    feeds: list[DaemonViewFeed] = []

    def say(text: str) -> None:
        if not quiet:
            bar.write(f"demo: {text}", file=sys.stderr)
        for feed in feeds:
            feed.progress(text)

    lockstep = args.speedup is None
    signing_key = demo_key(args)
    options = DaemonOptions(
        connect=["udpin:127.0.0.1:0"],
        seed=args.seed,
        steps=steps,
        discovery_timeout_s=30.0,
        ready_timeout_s=60.0,
        takeoff_timeout_s=60.0,
        lost_after_s=3.0 if lockstep else paced_lost_after_s(args.speedup),
        time_scale=RELEASED_SPEEDUP if lockstep else args.speedup,
        lockstep=lockstep,
        leg_timing=args.leg_timing,
        signing_key=signing_key,
        tlog_path=out / "mission.tlog",
        progress=say,
        on_step=on_step,
    )
    daemon = MissionDaemon(scenario, options)
    daemon.refuse_unkeepable_time_scale()  # paced: a speedup it cannot keep, before the sim
    view = ViewSession(
        scenario, seed=args.seed, steps=steps, uav_count=scenario.uav_count, source="mavlink",
        truth=True, out_dir=out, options=view_options(args),
    )  # fmt: skip
    truth = TruthReceiver()  # the simulator's true targets, for the view only
    feeds.append(DaemonViewFeed(daemon, view, truth.latest))
    options.step_listeners.append(feeds[0].listener)
    if signing_key is None:  # said even with --json (on stderr), like the view's address
        fix = "drop --no-signing to sign with a key made for the mission"
        bar.write(f"demo: warning: {unsigned_warning(fix)}", file=sys.stderr)
    if view.url is not None:  # printed even with --json (on stderr): the way to open it
        bar.write(f"demo: live view at {view.url}", file=sys.stderr)
    try:
        link = daemon.connect()
    except BaseException:
        view.close()
        view.stop()
        truth.close()
        raise
    port = link.endpoints[0].port
    sim_log = out / "sim.log"
    truth_path = out / "target_truth.json"
    truth_path.unlink(missing_ok=True)  # a file from an earlier run must not be joined
    sim = start_simulator(
        args.scenario, args.seed, args.speedup, port, sim_log, truth_path, truth.port,
        signing_key,
    )  # fmt: skip
    say(
        f"simulator started (pid {sim.pid}, {scenario.uav_count} vehicles, "
        f"{'lockstep' if lockstep else f'{args.speedup:g}x'}, "
        f"{'unsigned' if signing_key is None else 'signed'}) -> udp {port}"
    )
    started = time.monotonic()
    signals = MissionSignals()
    try:
        with signals:
            report = daemon.fly()
    except MissionInterrupted:  # Ctrl-C / SIGTERM: RTL was sent; write what was flown
        if daemon.report is None:
            raise
        report = daemon.report
    except UserError as exc:
        if sim.poll() is not None:
            raise UserError(
                f"the simulator exited (status {sim.returncode}): "
                f"{last_line(sim_log) or 'no output'}"
            ) from None
        heard = len(link.vehicles)
        if isinstance(exc, DiscoveryError) and heard < scenario.uav_count:
            # the daemon's advice (start them, check where they send to) is not the demo's
            raise UserError(
                f"the demo's simulator (pid {sim.pid}) was not heard within "
                f"{options.discovery_timeout_s:g} s of its start ({heard} of "
                f"{scenario.uav_count} vehicles): the machine is too busy to start it in time, "
                f"or the process is stopped; run the demo again on a less loaded machine (the "
                f"simulator's log: {sim_log})"
            ) from None
        raise
    finally:
        bar.close()
        stop_simulator(sim)
        view.close()
        view.stop()
        truth.close()
    result = report.result
    result["wall_time_s"] = time.monotonic() - started
    join_target_account(result, truth_path, scenario.config.step_s, say)
    summary = simulator_summary(sim_log)
    if summary is not None and "safety" in summary:
        result["simulator_truth"] = summary["safety"]  # what really flew, every physics tick
    written = write_mission_outputs(result, out)
    status = signals.exit_status if signals.received else 0
    if quiet:
        print(json.dumps(result))
        return status
    if signals.received:
        print(f"demo: interrupted ({signals.received}); what was flown is written", file=sys.stderr)
    if result.get("steps"):
        print(format_summary(result))
    if result.get("target_account"):
        print(format_account(result["target_account"]))
    for line in lost_vehicle_lines(result):
        print(line)
    others = [
        p for p in (out / "mission.tlog", sim_log, truth_path, replay_path(out)) if p.exists()
    ]
    print(written_line(out, [*written, *others]))
    return status
