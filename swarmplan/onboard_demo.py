"""``swarmplan demo SCENARIO --onboard``: the swarm without a centre on one machine. Starts the
simulator (paced, each vehicle with its own port, the radio between them), one ``swarmplan
node`` process per UAV beside its vehicle, and this coordinator, which listens to the swarm link
as a ground station (the simulator's radio passes what a ground antenna at the area's centre
hears to the coordinator's port: ``mavlink_bridge.mission.swarm_watch``), says the progress and
feeds the live view from what it hears, then joins the nodes' parts (``node-I/result.json``)
into the usual result folder and summary (``result.json``: ``architecture`` onboard, the link's
figures, and what the coordinator heard).

The simulator and the nodes run in sessions of their own: killing the coordinator (Ctrl-C in
its terminal, SIGTERM, SIGKILL) stops neither; the nodes fly on and bring the planes home, each
writing its own part, and the simulator stops itself after the mission's simulated time
(``--duration-s``). Time is paced (``--speedup``), never lockstep: a lockstep simulator
advances only on one ground station's grants, and a coordinator that may die cannot be that
clock; each node follows its own vehicle's clock, as on real planes.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mavlink_bridge.mission.swarm_watch import GroundEar, HeardSwarm, SwarmWatch, progress_line
from mavlink_wire.signing import key_environment
from mission_view.truth_receiver import TruthReceiver
from mission_view.view_session import ViewSession
from planner.scenario import Scenario
from sim_gateway.sim_options import RadioOptions
from swarmplan import option_groups
from swarmplan.arguments import finite_float
from swarmplan.sim_log import simulator_summary

#: the default pace of an onboard demo: each node must hear its neighbours and decide within a
#: share of the decision period, N processes on the machine's cores
ONBOARD_SPEEDUP = 4.0
#: simulated seconds the simulator runs on beyond the mission's steps (boot, take-off, the
#: flight home and its watch), after which it stops itself if no coordinator stopped it
SIM_MARGIN_S = 600.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``swarmplan demo``'s options of the swarm without a centre."""
    onboard = parser.add_argument_group(
        "onboard", "one planner per UAV, no centre (docs/onboard.md): one `swarmplan node` "
        "process per UAV beside its vehicle, a coordinator that only watches and joins"
    )  # fmt: skip
    onboard.add_argument(
        "--onboard", action="store_true",
        help="fly the swarm without a centre (paced: --speedup, default 4)",
    )  # fmt: skip
    onboard.add_argument(
        "--radio-range-km",
        type=finite_float,
        default=None,
        metavar="KM",
        help="--onboard: the swarm radio's range (default unlimited)",
    )
    onboard.add_argument(
        "--radio-loss",
        type=finite_float,
        default=0.0,
        metavar="P",
        help="--onboard: each receiver loses each frame with probability P",
    )
    onboard.add_argument(
        "--join", action="store_true",
        help="--onboard: fly nothing, join the nodes' parts already in --out (after the "
        "coordinator was killed and the nodes finished) into result.json",
    )  # fmt: skip


#: where the demo's per-vehicle ports are drawn from: below Linux's ephemeral range (32768 and
#: up), from which every socket bound to port 0 (the simulator's own, the coordinator's ear, any
#: other program's) takes its port, so none of those can take a vehicle's port between its
#: choice here and its node's bind (a node was refused its port so in one CI run)
PORT_RANGE = (20000, 32700)


def free_port_block(count: int, host: str = "127.0.0.1") -> int:
    """A base port with ``count`` consecutive free UDP ports from it (checked by binding),
    drawn at random from :data:`PORT_RANGE`."""
    draw = random.Random()
    for _ in range(200):
        base = draw.randrange(PORT_RANGE[0], PORT_RANGE[1] - count)
        held = []
        try:
            for port in range(base, base + count):
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                held.append(s)
                s.bind((host, port))
            return base
        except OSError:
            continue
        finally:
            for s in held:
                s.close()
    raise OSError(f"no {count} consecutive free UDP ports on {host}")


def _python(*args: str) -> list[str]:
    return [sys.executable, "-m", "swarmplan", *args]


def _start(command: list[str], log: Path, key: bytes | None) -> subprocess.Popen:
    """A process in a session of its own (a signal to the coordinator does not reach it)."""
    with open(log, "wb") as sink:
        return subprocess.Popen(
            command, stdout=sink, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env={**os.environ, **key_environment(key)}, start_new_session=True,
        )  # fmt: skip


def start_swarm(
    args: Any, scenario: Scenario, steps: int, out: Path, key: bytes | None,
    ground_port: int | None = None, truth_port: int | None = None,
) -> tuple[subprocess.Popen, list[subprocess.Popen], float]:  # fmt: skip
    """The simulator and one node per UAV; returns them and the speedup. ``ground_port``:
    where the simulator's ground radio passes what it hears of the swarm link (the
    coordinator's ear); ``truth_port``: where it sends the true targets (the live view's)."""
    radio = RadioOptions(
        math.inf if args.radio_range_km is None else args.radio_range_km, args.radio_loss
    )
    radio.validate()
    speedup = args.speedup or ONBOARD_SPEEDUP
    n = scenario.uav_count
    base = free_port_block(n)
    duration = steps * scenario.config.step_s + SIM_MARGIN_S
    sim_cmd = _python(
        "sim", "--scenario", args.scenario, "--seed", str(args.seed), "--speedup", f"{speedup:g}",
        "--per-vehicle-ports", str(base), "--radio-loss", f"{radio.loss:g}", "--quiet",
        "--duration-s", f"{duration:g}", "--target-account", str(out / "target_truth.json"),
        *([] if math.isinf(radio.range_km) else ["--radio-range-km", f"{radio.range_km:g}"]),
        *([] if ground_port is None else ["--radio-ground-port", str(ground_port)]),
        *([] if truth_port is None else ["--truth-port", str(truth_port)]),
    )  # fmt: skip
    sim = _start(sim_cmd, out / "sim.log", key)
    nodes = []
    for i in range(n):
        folder = out / f"node-{i}"
        folder.mkdir(parents=True, exist_ok=True)
        node_cmd = _python(
            "node", args.scenario, "--connect", f"udpin:127.0.0.1:{base + i}", "--uav", str(i),
            "--seed", str(args.seed), "--steps", str(steps), "--time-scale", f"{speedup:g}",
            "--out", str(folder),
            *([] if args.leg_timing else ["--no-leg-timing"]),
        )  # fmt: skip
        nodes.append(_start(node_cmd, folder / "node.log", key))
    return sim, nodes, speedup


def watch(nodes: Sequence[subprocess.Popen], ear: SwarmWatch, steps: int, quiet: bool) -> None:
    """Until every node has exited: hear the swarm, show its steps, and say the newest step
    heard when it (or the nodes running, or who is silent) changes."""
    said = None
    swarm = ear.swarm
    while any(p.poll() is None for p in nodes):
        ear.pump(0.2)
        now = time.monotonic()
        running = sum(p.poll() is None for p in nodes)
        silent = () if swarm.shown < 0 else tuple(i for i, _ in swarm.silent(now))
        key = (swarm.shown, running, silent)
        if key != said and not quiet:
            print(progress_line(swarm, steps, running, now), file=sys.stderr, flush=True)
            said = key
    ear.pump(0.0, flush=True)  # the steps heard but not shown yet


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def _sum_dicts(rows: list[dict[str, int]]) -> dict[str, int]:
    total: dict[str, int] = {}
    for row in rows:
        for name, value in row.items():
            total[name] = total.get(name, 0) + int(value)
    return total


def join_parts(out: Path, scenario: Scenario, seed: int, sim_summary: dict | None) -> dict:
    """The swarm's result from the nodes' parts (a missing part is said, not guessed)."""
    parts, missing = {}, []
    for i in range(scenario.uav_count):
        try:
            parts[i] = json.loads((out / f"node-{i}" / "result.json").read_text())
        except (OSError, ValueError):
            missing.append(i)
    uavs, engagements, observed = [], [], set()
    for i, part in parts.items():
        for row in part.get("uavs", []):
            uavs.append({**row, "id": i})
        engagements += [{**e, "uav": i, "system_id": i + 1} for e in part.get("engagements", [])]
        observed |= set(part.get("observed_cells", []))
    cfg = scenario.config
    links = {i: p.get("link", {}) for i, p in parts.items()}
    sent = [b for link in links.values() for b in link.get("bytes_sent", [])]
    cpu = [link.get("cpu_s_per_step", {}).get("mean", 0.0) for link in links.values()]
    result: dict[str, Any] = {
        "scenario": scenario.name, "seed": seed, "architecture": "onboard",
        "algorithm": "hapf-aco-onboard", "uav_count": scenario.uav_count,
        "steps": max((p.get("steps", 0) for p in parts.values()), default=0),
        "nodes_missing": missing,
        "ended": {i: p.get("ended") for i, p in parts.items()},
        "coverage": len(observed) / float(cfg.grid_nx * cfg.grid_ny),
        "engagements": sorted(engagements, key=lambda e: (e.get("step", 0), e["uav"])),
        "engaged_count": len({e.get("target_id") for e in engagements}),
        "returned_count": sum(int(p.get("returned_count", 0)) for p in parts.values()),
        "violations": _sum_dicts([p.get("violations", {}) for p in parts.values()]),
        "uavs": uavs,
        "link": {
            "bytes_sent_per_uav_per_step": {
                "mean": round(sum(sent) / max(len(sent), 1), 1), "max": max(sent, default=0)},
            "messages_missed": sum(k.get("messages_missed", 0) for k in links.values()),
            "claim_deadlines": _sum_dicts([k.get("claim_deadlines", {}) for k in links.values()]),
            "phase_timeouts": _sum_dicts([k.get("phase_timeouts", {}) for k in links.values()]),
            "cpu_s_per_node_step_mean": round(sum(cpu) / max(len(cpu), 1), 4),
            "radio": None if sim_summary is None else sim_summary.get("radio"),
            "nodes": links,
        },
    }  # fmt: skip
    if sim_summary is not None and "safety" in sim_summary:
        result["simulator_truth"] = sim_summary["safety"]
    return result


def _truth_line(result: dict) -> str:
    """What really flew: the simulator's truth, or (real autopilots) the radio relay's
    separation between the airborne planes, from their own reports."""
    truth, radio = result.get("simulator_truth") or {}, result["link"].get("radio") or {}
    if not truth and "min_separation_km" in radio:
        separation = radio["min_separation_km"]
        return f"  radio relay   min separation {separation} km (airborne planes' own reports)"
    return (
        f"  simulator     threat entries {truth.get('threat_entries')}, separation "
        f"{truth.get('separation_breaches')}, min separation {truth.get('min_separation_km')} km"
    )


def _heard_lines(result: dict) -> list[str]:
    """What the coordinator heard over the swarm link (none after ``--join``)."""
    heard = result.get("coordinator")
    if not heard:
        return []
    return [
        f"heard           {heard['reports']} reports over the swarm link, coverage "
        f"{heard['coverage_heard'] * 100:.1f}%, engaged {heard['engaged_heard']}, last step "
        f"heard per UAV {heard['last_step_heard']} (the coordinator's ground radio)"
    ]


def summary_lines(result: dict, out: Path) -> list[str]:
    link = result["link"]
    deadlines = link["claim_deadlines"]
    radio = link.get("radio") or {}
    logs = "radio-relay.log" if "not_relayed" in radio else "sim.log"
    return [
        f"architecture    onboard: {result['uav_count']} nodes, no ground station needed",
        f"steps           {result['steps']}",
        f"coverage        {result['coverage'] * 100:.1f}% (union of the nodes' looks)",
        f"engaged         {result['engaged_count']}",
        f"at home         {result['returned_count']} of {result['uav_count']}",
        f"violations      {', '.join(f'{k} {v}' for k, v in result['violations'].items())}",
        _truth_line(result),
        f"link            {link['bytes_sent_per_uav_per_step']['mean']:g} B per UAV per step "
        f"(max {link['bytes_sent_per_uav_per_step']['max']}); radio lost to range "
        f"{radio.get('lost_to_range', 0)}, to loss {radio.get('lost_to_loss', 0)}; "
        f"messages missed {link['messages_missed']}",
        f"claim deadlines missed {deadlines.get('missed', 0)}: avoided "
        f"{deadlines.get('avoided', 0)}, held {deadlines.get('held', 0)}",
        f"nodes missing   {result['nodes_missing'] or 'none'}",
        *_heard_lines(result),
        f"files in        {out}/ (result.json, node-I/result.json, {logs}"
        f"{', replay.jsonl.gz' if (out / 'replay.jsonl.gz').exists() else ''})",
    ]


def open_view(
    args: Any, scenario: Scenario, steps: int, out: Path
) -> tuple[ViewSession, TruthReceiver]:
    """The mission view of what the coordinator hears (replay in ``out``, served unless
    ``--no-view``) and the receiver of the simulator's true targets, for the view only."""
    view = ViewSession(
        scenario, seed=args.seed, steps=steps, uav_count=scenario.uav_count, source="mavlink",
        truth=True, out_dir=out, options=option_groups.view_options(args),
    )  # fmt: skip
    return view, TruthReceiver()


def heard_summary(watch: SwarmWatch) -> dict[str, Any]:
    """What the coordinator heard of the swarm link (result.json's ``coordinator``)."""
    swarm, ear = watch.swarm, watch.ear
    return {
        "heard_by": "ground radio at the area's centre (the simulator's radio model)",
        "frames": ear.frames,
        "reports": swarm.reports,
        "undecodable": swarm.undecodable,
        "steps_shown": swarm.shown + 1,
        "coverage_heard": round(float(swarm.coverage.any(axis=0).mean()), 4),
        "engaged_heard": len(swarm.engaged),
        "last_step_heard": [u.step for u in swarm.uavs],
        "wire": dict(vars(ear.reassembler.stats)),
    }


def main(args: Any, scenario: Scenario, out: Path, key: bytes | None) -> int:
    """Start the swarm, hear it, join the parts (``swarmplan demo --onboard``)."""
    if args.join:
        return write_joined(args, scenario, out, {})
    steps = args.steps or scenario.steps
    started = time.monotonic()
    view, truth = open_view(args, scenario, steps, out)
    ear = GroundEar(key)
    try:
        sim, nodes, speedup = start_swarm(args, scenario, steps, out, key, ear.port, truth.port)
        # (said also with --json: the pids are how to reach the processes it leaves running)
        print(f"coordinator: simulator pid {sim.pid} ({scenario.uav_count} vehicles, "
              f"{speedup:g}x, radio range {args.radio_range_km or 'unlimited'} km, loss "
              f"{args.radio_loss:g}, {'unsigned' if key is None else 'signed'})",
              file=sys.stderr)  # fmt: skip
        print(f"coordinator: node pids {' '.join(str(p.pid) for p in nodes)} (node i flies "
              f"system id i+1; its log: {out}/node-i/node.log)", file=sys.stderr)  # fmt: skip
        if view.url is not None:
            print(f"coordinator: live view at {view.url} (what the ground radio hears)",
                  file=sys.stderr)  # fmt: skip
        sys.stderr.flush()
        swarm = HeardSwarm(scenario, args.seed, scenario.config.step_s / speedup, ear.signed)
        heard = SwarmWatch(ear, swarm, view.post, truth.latest)
        view.phase("search: the nodes fly the swarm (heard over the swarm link)", -1)
        watch(nodes, heard, steps, args.json)
        stop(sim)  # (its summary, with the radio's count and the truth of what flew, is in sim.log)
    except BaseException:  # (Ctrl-C: the nodes and the simulator fly on; the view stops)
        view.stop()
        raise
    finally:
        view.close()
        ear.close()
        truth.close()
    try:
        return write_joined(args, scenario, out, {
            "wall_time_s": round(time.monotonic() - started, 1), "speedup": speedup,
            "coordinator": heard_summary(heard)})  # fmt: skip
    finally:
        view.stop()


#: where ``swarmplan radio-relay``'s output goes in a result folder of nodes on real autopilots
#: (docs/onboard.md, "On a companion computer"): ``--join`` takes the radio's count from it
RELAY_LOG = "radio-relay.log"


def write_joined(args: Any, scenario: Scenario, out: Path, extra: dict[str, Any]) -> int:
    """Join the parts in ``out`` (with the simulator's summary, when it wrote one), write
    result.json, say the summary; exit status 1 when a node's part is missing."""
    sim = simulator_summary(out / "sim.log")
    if sim is None:  # real autopilots: the radio relay's count, when its log is there
        relay = simulator_summary(out / RELAY_LOG)
        sim = None if relay is None else {"radio": relay}
    result = join_parts(out, scenario, args.seed, sim)
    result.update(extra)
    (out / "result.json").write_text(json.dumps(result, indent=1, default=float))
    if args.json:
        print(json.dumps(result, default=float))
    else:
        print("\n".join(summary_lines(result, out)))
    return 0 if not result["nodes_missing"] else 1
