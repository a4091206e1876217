"""Reliability measured on the continuous telemetry: link loss, pacing, ground-station outages.

    nice -n 10 python benchmarks/bench_reliability.py [--part loss|outage|all] [--runs 10]
                                                       [--steps 8] [--out runs/bench-reliability]

Real processes on loopback: ``swarmplan sim`` and ``swarmplan daemon`` (``--json``), a short
mission of three planes among two threats (``SCENARIO`` below: starts 3-4 km from a threat
edge, so the planes fly and circle near them). Every figure comes from the flown tracks: the
daemon's account along every position report (``track_audit``: threat entries, separation
breaches, minimum separation and threat margin, per phase) and the simulator's own per-tick
ground truth (``safety`` in its summary). Per-decision-step violations are printed alongside.

* ``loss``: 10 / 20 / 30 % loss each way (plus 0-100 ms jitter, 2 % duplicated, 2 % reordered,
  ``tests/reliability/udp_fault_relay.py``), in lockstep and paced at 1x, 5x and 20x; one run
  each per relay seed (``--losses 20,30 --paces 20 --seeds 1,2,3``: only those).
* ``outage``: the daemon is stopped (SIGSTOP) after its 3rd step for 3, 10, 30 and 120 s of wall
  time, the vehicles paced at ``--outage-speedup`` (default 20x: 60 s to 40 min of flight
  without a ground station), then
  continued (SIGCONT); ``--runs`` runs each (default 10). The vehicles' GCS failsafe acts after
  FS_LONG_TIMEOUT (5 s); a zero in "entries" is what must hold.

Prints one markdown table per part (docs/reliability.md) and the machine's load average, and
writes every run's result and simulator summary to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO / "tests"), str(REPO / "tests" / "reliability")]

from loopback import env, free_udp_port, start_swarmplan, stop  # noqa: E402
from reliability_harness import last_json  # noqa: E402
from udp_fault_relay import FaultProfile, FaultRelay  # noqa: E402

SCENARIO = """
name = "bench-near-threats"
description = "three planes in a 30 km square between two threats (bench_reliability.py)"
steps = 8
altitude_m = 500
[parameters]
grid_nx = 30
grid_ny = 30
[uavs]
count = 3
[[uavs.start]]
x_km = 8.5
y_km = 4.5
heading_deg = 90
[[uavs.start]]
x_km = 15.5
y_km = 4.5
heading_deg = 90
[[uavs.start]]
x_km = 22.5
y_km = 4.5
heading_deg = 90
[[targets]]
id = 1
kind = "unknown_position"
x_km = 15
y_km = 25
value = 1
[[threats]]
x_km = 10.0
y_km = 12.0
radius_km = 3.5
[[threats]]
x_km = 21.0
y_km = 13.0
radius_km = 3.5
"""


def _wait_step(out_log: Path, step: int, timeout_s: float, procs: list) -> bool:
    """Until the daemon's progress line shows ``step`` (its stderr log)."""
    deadline = time.monotonic() + timeout_s
    mark = f"step {step:>4}/"
    while time.monotonic() < deadline:
        if mark in out_log.read_text(errors="replace"):
            return True
        if any(p.poll() is not None for p in procs):
            return False
        time.sleep(0.05)
    return False


def fly(
    work: Path,
    name: str,
    steps: int,
    speedup: float | None,
    profile: FaultProfile | None = None,
    outage_s: float = 0.0,
    seed: int = 1,
) -> dict:
    """One mission; returns the row's figures. ``speedup`` None: lockstep."""
    run = work / name
    run.mkdir(parents=True, exist_ok=True)
    scenario = work / "scenario.toml"
    port = free_udp_port()
    relay = None
    pace = ["--lockstep", "--speedup", "100"] if speedup is None else ["--speedup", f"{speedup:g}"]
    sim_args = ["sim", "--scenario", str(scenario), "--boot-s", "2", "--quiet", *pace]
    if profile is not None:
        relay = FaultRelay(port, 3, profile, seed=seed)
        relay.start()
        sim_args += ["--per-vehicle-ports", str(relay.base_port)]
    else:
        sim_args += ["--gcs-port", str(port)]
    daemon_args = [
        "daemon", "--connect", f"udpin:127.0.0.1:{port}", "--scenario", str(scenario),
        "--steps", str(steps), "--out", str(run / "out"), "--timeout", "60",
        "--lost-after", "10",
    ]  # fmt: skip
    daemon_args += ["--lockstep"] if speedup is None else ["--time-scale", f"{speedup:g}"]
    sim_log, daemon_log = run / "sim.log", run / "daemon.log"
    started = time.monotonic()
    sim = start_swarmplan(sim_args, sim_log)
    daemon = start_swarmplan(daemon_args, daemon_log)
    try:
        if outage_s > 0 and _wait_step(daemon_log, 3, 120, [sim, daemon]):
            daemon.send_signal(signal.SIGSTOP)
            time.sleep(outage_s)
            daemon.send_signal(signal.SIGCONT)
        daemon.wait(600 + outage_s)
    except subprocess.TimeoutExpired:
        pass
    finally:
        stop(daemon)
        stop(sim)
        if relay is not None:
            relay.stop()
    wall = time.monotonic() - started
    result_path = run / "out" / "result.json"
    result = json.loads(result_path.read_text()) if result_path.exists() else None
    truth = (last_json(sim_log) or {}).get("safety")
    return {"name": name, "wall_s": wall, "result": result, "truth": truth,
            "relay": None if relay is None else relay.counters.__dict__}  # fmt: skip


def _km(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def row(figures: dict) -> str:
    r, t = figures["result"], figures["truth"]
    if r is None or t is None or "violations" not in r:
        # no result, or a mission that ended before it flew (its launch failed: a refused
        # speedup, an upload or a parameter that did not get through)
        why = "see its logs" if r is None else str(r.get("ended", "see its logs"))
        return f"| {figures['name']} | failed ({why}) |" + " |" * 10
    a = r["track_audit"]["all"]
    v = r["violations"]
    phases = r["track_audit"]["phases"]
    by_phase = ", ".join(
        f"{k} {p['threat_entries']}/{p['separation_breaches']}" for k, p in phases.items()
    )
    return (
        f"| {figures['name']} | {figures['wall_s']:.0f} | {r['steps']} | "
        f"{a['threat_entries']} / {a['separation_breaches']} | {_km(a['min_threat_margin_km'])}"
        f" | {_km(a['min_separation_km'])} | {t['threat_entries']} / {t['separation_breaches']}"
        f" | {_km(t['min_threat_margin_km'])} / {_km(t['min_separation_km'])} | "
        f"{v['threat']}/{v['separation']}/{v['turn']} | {r.get('held_steps', '-')} | "
        f"{len(r.get('lost_uavs') or [])} | {by_phase} |"
    )


HEADER = (
    "| run | wall s | steps | tracks: threat entries / sep. breaches | tracks: min threat margin "
    "km | tracks: min sep km | sim truth: entries / breaches | sim truth: margin / sep km | "
    "per step threat/sep/turn | held steps | lost | per phase (entries/breaches) |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("loss", "outage", "all"), default="all")
    parser.add_argument("--runs", type=int, default=10, help="runs per outage length")
    parser.add_argument("--steps", type=int, default=8)
    parser.add_argument("--outages", default="3,10,30,120", help="outage lengths, wall s")
    parser.add_argument("--losses", default="10,20,30", help="loss each way, percent")
    parser.add_argument(
        "--paces", default="lockstep,1,5,20", help="lockstep and/or speedups of the loss runs"
    )
    parser.add_argument(
        "--seeds", default="1", help="the fault relay's seeds: one loss run per seed (1,2,3)"
    )
    parser.add_argument(
        "--outage-speedup", type=float, default=20.0,
        help="the vehicles' speedup in the outage runs (a loaded machine's daemon refuses 20x)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=REPO / "runs" / "bench-reliability")
    args = parser.parse_args()
    work: Path = args.out
    work.mkdir(parents=True, exist_ok=True)
    (work / "scenario.toml").write_text(SCENARIO)
    os.environ.update(env())
    print(f"load average at start: {os.getloadavg()[0]:.1f} ({os.cpu_count()} cores)", flush=True)
    rows: list[dict] = []
    if args.part in ("loss", "all"):
        print("\n### Link loss\n\n" + HEADER, flush=True)
        paces = [None if p == "lockstep" else float(p) for p in args.paces.split(",")]
        for loss in (float(x) / 100 for x in args.losses.split(",")):
            profile = FaultProfile(loss=loss, jitter_s=0.1, duplicate=0.02, reorder=0.02)
            for speedup in paces:
                for seed in (int(x) for x in args.seeds.split(",")):
                    pace = "lockstep" if speedup is None else f"paced {speedup:g}x"
                    name = f"loss {loss:.0%} {pace}" + (f" seed {seed}" if seed != 1 else "")
                    figures = fly(work, name.replace(" ", "_").replace("%", ""), args.steps,
                                  speedup, profile, seed=seed)  # fmt: skip
                    figures["name"] = name
                    rows.append(figures)
                    print(row(figures), flush=True)
    if args.part in ("outage", "all"):
        print(f"\n### GCS outages (daemon stopped after step 3, vehicles at "
              f"{args.outage_speedup:g}x)\n\n" + HEADER)  # fmt: skip
        for outage in (float(x) for x in args.outages.split(",")):
            entries = 0
            for k in range(args.runs):
                name = f"outage {outage:g} s #{k + 1}"
                figures = fly(work, f"outage_{outage:g}_{k + 1}", args.steps,
                              args.outage_speedup, outage_s=outage)  # fmt: skip
                figures["name"] = name
                rows.append(figures)
                print(row(figures), flush=True)
                t = figures["truth"]
                entries += 0 if t is None else t["threat_entries"]
            print(f"| outage {outage:g} s: {args.runs} runs, simulator threat entries in all: "
                  f"{entries} |", flush=True)  # fmt: skip
    (work / "runs.json").write_text(json.dumps(rows, indent=1, default=str))
    print(f"\nload average at end: {os.getloadavg()[0]:.1f}; runs in {work}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
