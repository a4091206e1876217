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
from dataclasses import dataclass
from pathlib import Path

from mavlink_bridge.mission.daemon import (
    DaemonOptions,
    MissionDaemon,
    MissionInterrupted,
    StepStatus,
)
from mavlink_bridge.mission.view_feed import DaemonViewFeed
from mavlink_bridge.results.mission_result import MissionReport, lost_vehicle_lines
from mavlink_bridge.vehicles.discovery import DiscoveryError
from mavlink_bridge.vehicles.vehicle_loss import paced_lost_after_s
from mavlink_wire.signing import key_environment, load_signing_key, mission_key, unsigned_warning
from mission_view.replay_file import replay_path
from mission_view.truth_receiver import TruthReceiver
from mission_view.view_session import ViewOptions, ViewSession
from planner.errors import UserError
from planner.metrics import format_summary
from planner.scenario import Scenario, load_scenario
from sim_gateway.target_account import account_of_ground_station, format_account
from swarmplan import onboard_demo, option_groups
from swarmplan.arguments import positive_float, writable_folder
from swarmplan.daemon_command import write_mission_outputs
from swarmplan.interrupts import MissionSignals
from swarmplan.run_command import progress_bar, written_line
from swarmplan.sim_log import simulator_summary

HELP = "fly a scenario end to end: the MAVLink simulator and the planner daemon on loopback UDP"

#: By default the simulator runs in lockstep with the daemon (``swarmplan sim --lockstep``): as
#: fast as both can go, and the same seed gives the same flight and result. ``--speedup X`` paces
#: it at X simulated seconds per wall second instead (what a SITL run looks like; not repeatable).
#: After the mission (RTL) a lockstep simulator runs on at this speed until it is stopped.
RELEASED_SPEEDUP = 100.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    option_groups.add_scenario_argument(parser, "paper-10uav", positional=True)
    option_groups.add_seed_argument(parser, "seed of the world and the planner")
    option_groups.add_steps_option(parser)
    parser.add_argument(
        "--speedup",
        type=positive_float,
        default=None,
        help="pace the simulator at this many simulated seconds per wall second instead of "
        "lockstep (default: lockstep, as fast as possible and repeatable for a seed)",
    )
    parser.add_argument(
        "--timeout",
        type=positive_float,
        default=30.0,
        help="seconds to wait for the simulator's vehicles to be heard (default 30; more on a "
        "busy machine)",
    )
    option_groups.add_out_option(parser, "runs/<scenario>-seed<S>-demo")
    onboard_demo.add_arguments(parser)
    option_groups.add_leg_timing_option(parser)
    signing = parser.add_mutually_exclusive_group()
    signing.add_argument(
        "--no-signing",
        action="store_true",
        help="fly without MAVLink 2 signing (default: the simulator and the daemon sign with a "
        "key made for this mission, kept in memory only)",
    )
    option_groups.add_signing_key_option(
        signing,
        "the simulator and the daemon sign with it",
        otherwise="a key made for this mission",
    )
    option_groups.add_view_options(parser)
    option_groups.add_json_option(parser)


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


class DemoDisplay:
    """What a person sees of a demo: the progress bar and the lines said on stderr, and the
    live view (fed by the daemon, with the simulator's true targets)."""

    def __init__(self, steps: int, title: str, quiet: bool) -> None:
        self.quiet = quiet
        self.bar = progress_bar(steps, title, quiet)
        self.feeds: list[DaemonViewFeed] = []
        self.view: ViewSession | None = None
        self.truth: TruthReceiver | None = None

    def on_step(self, status: StepStatus) -> None:
        if status.step > 0:  # step 0 is the start: the bar counts decision steps
            self.bar.update(1)
        self.bar.set_postfix_str(
            f"coverage {status.coverage * 100:.1f}% engaged {status.engaged} active {status.active}"
        )

    def say(self, text: str) -> None:
        """A progress line (not with --json), and to the live view."""
        if not self.quiet:
            self.bar.write(f"demo: {text}", file=sys.stderr)
        for feed in self.feeds:
            feed.progress(text)

    def warn(self, text: str) -> None:
        """A line on stderr even with --json (which prints only the result on stdout)."""
        self.bar.write(f"demo: {text}", file=sys.stderr)

    def open_view(
        self, scenario: Scenario, seed: int, steps: int, out: Path, options: ViewOptions,
        daemon: MissionDaemon,
    ) -> None:  # fmt: skip
        """The mission view (replay in ``out``, served unless ``--no-view``) fed by ``daemon``
        and by the simulator's true targets (a UDP port of this process)."""
        self.view = ViewSession(
            scenario, seed=seed, steps=steps, uav_count=scenario.uav_count, source="mavlink",
            truth=True, out_dir=out, options=options, actions=daemon.operator.inbox,
        )  # fmt: skip
        self.truth = TruthReceiver()  # the simulator's true targets, for the view only
        feed = DaemonViewFeed(daemon, self.view, self.truth.latest)
        self.feeds.append(feed)
        daemon.options.step_listeners.append(feed.listener)

    def close_view(self) -> None:
        if self.view is not None:
            self.view.close()
            self.view.stop()
        if self.truth is not None:
            self.truth.close()


def demo_options(
    args: argparse.Namespace, steps: int, out: Path, signing_key: bytes | None,
    display: DemoDisplay,
) -> DaemonOptions:  # fmt: skip
    """The daemon's options in a demo: one loopback port for the simulator, lockstep unless
    ``--speedup``, progress to ``display``."""
    lockstep = args.speedup is None
    return DaemonOptions(
        connect=["udpin:127.0.0.1:0"],
        seed=args.seed,
        steps=steps,
        discovery_timeout_s=args.timeout,
        ready_timeout_s=60.0,
        takeoff_timeout_s=60.0,
        lost_after_s=3.0 if lockstep else paced_lost_after_s(args.speedup),
        time_scale=RELEASED_SPEEDUP if lockstep else args.speedup,
        lockstep=lockstep,
        leg_timing=args.leg_timing,
        signing_key=signing_key,
        tlog_path=out / "mission.tlog",
        progress=display.say,
        on_step=display.on_step,
    )


@dataclass
class DemoFlight:
    """A flown demo: the daemon's report, the signals that came, the simulator's files."""

    report: MissionReport
    signals: MissionSignals
    sim_log: Path
    truth_path: Path
    started: float  # time.monotonic() when the simulator was started


def fly_with_simulator(
    args: argparse.Namespace, scenario: Scenario, daemon: MissionDaemon, display: DemoDisplay,
    out: Path, signing_key: bytes | None,
) -> DemoFlight:  # fmt: skip
    """Start the simulator sending to the daemon's port, fly, and stop it on every way out
    (an interrupted flight returns what was flown)."""
    try:
        link = daemon.connect()
    except BaseException:
        display.close_view()
        raise
    port = link.endpoints[0].port
    sim_log = out / "sim.log"
    truth_path = out / "target_truth.json"
    truth_path.unlink(missing_ok=True)  # a file from an earlier run must not be joined
    sim = start_simulator(
        args.scenario, args.seed, args.speedup, port, sim_log, truth_path,
        display.truth.port if display.truth is not None else None, signing_key,
    )  # fmt: skip
    pace = "lockstep" if args.speedup is None else f"{args.speedup:g}x"
    display.say(
        f"simulator started (pid {sim.pid}, {scenario.uav_count} vehicles, {pace}, "
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
        heard = len(link.vehicles)
        explained = simulator_failure(exc, sim, sim_log, heard, scenario, daemon.options)
        if explained is None:
            raise
        raise explained from None
    finally:
        display.bar.close()
        stop_simulator(sim)
        display.close_view()
    return DemoFlight(report, signals, sim_log, truth_path, started)


def simulator_failure(
    exc: UserError, sim: subprocess.Popen, sim_log: Path, heard: int, scenario: Scenario,
    options: DaemonOptions,
) -> UserError | None:  # fmt: skip
    """The demo's own account of a failed flight when its simulator is the cause (it exited,
    or was not heard in time); None when the daemon's error says it best."""
    if sim.poll() is not None:
        return UserError(
            f"the simulator exited (status {sim.returncode}): {last_line(sim_log) or 'no output'}"
        )
    if isinstance(exc, DiscoveryError) and heard < scenario.uav_count:
        # the daemon's advice (start them, check where they send to) is not the demo's
        return UserError(
            f"the demo's simulator (pid {sim.pid}) was not heard within "
            f"{options.discovery_timeout_s:g} s of its start ({heard} of "
            f"{scenario.uav_count} vehicles): the machine is too busy to start it in time, "
            f"or the process is stopped; run the demo again on a less loaded machine (the "
            f"simulator's log: {sim_log})"
        )
    return None


def demo_result(flight: DemoFlight, scenario: Scenario, say: Callable[[str], None]) -> dict:
    """The daemon's result with the demo's additions: the wall time, the per-target account
    (joined with the simulator's truth) and what really flew, by the simulator's count."""
    result = flight.report.result
    result["wall_time_s"] = time.monotonic() - flight.started
    join_target_account(result, flight.truth_path, scenario.config.step_s, say)
    summary = simulator_summary(flight.sim_log)
    if summary is not None and "safety" in summary:
        result["simulator_truth"] = summary["safety"]  # what really flew, every physics tick
    return result


def print_demo_summary(result: dict, out: Path, written: list[Path], flight: DemoFlight) -> None:
    """The metrics, the per-target account, the lost vehicles and the files written."""
    if result.get("steps"):
        print(format_summary(result))
    if result.get("target_account"):
        print(format_account(result["target_account"]))
    for line in lost_vehicle_lines(result):
        print(line)
    others = [
        p
        for p in (out / "mission.tlog", flight.sim_log, flight.truth_path, replay_path(out))
        if p.exists()
    ]
    print(written_line(out, [*written, *others]))


def main(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    steps = args.steps or scenario.steps
    out = writable_folder(args.out or Path("runs") / f"{scenario.name}-seed{args.seed}-demo")
    if not args.onboard and (args.radio_range_km is not None or args.radio_loss or args.join):
        raise UserError("--radio-range-km, --radio-loss and --join need --onboard (the swarm "
                        "without a centre); add --onboard")  # fmt: skip
    if args.onboard:
        return onboard_demo.main(args, scenario, out, demo_key(args))
    display = DemoDisplay(steps, f"{scenario.name} over MAVLink", quiet=args.json)
    signing_key = demo_key(args)
    daemon = MissionDaemon(scenario, demo_options(args, steps, out, signing_key, display))
    daemon.refuse_unkeepable_time_scale()  # paced: a speedup it cannot keep, before the sim
    display.open_view(scenario, args.seed, steps, out, option_groups.view_options(args), daemon)
    if signing_key is None:  # said even with --json (on stderr), like the view's address
        display.warn(unsigned_warning("drop --no-signing to sign with a key made for the mission"))
    if display.view is not None and display.view.url is not None:
        display.warn(f"live view at {display.view.url}")  # the way to open it, even with --json
    flight = fly_with_simulator(args, scenario, daemon, display, out, signing_key)
    result = demo_result(flight, scenario, display.say)
    written = write_mission_outputs(result, out)
    status = flight.signals.exit_status if flight.signals.received else 0
    if args.json:
        print(json.dumps(result))
        return status
    if flight.signals.received:
        print(
            f"demo: interrupted ({flight.signals.received}); what was flown is written",
            file=sys.stderr,
        )
    print_demo_summary(result, out, written, flight)
    return status
