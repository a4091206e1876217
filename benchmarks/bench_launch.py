"""How long the daemon's launch takes against the swarm's size, and a swarm of more than one
MAVLink network flown end to end.

    python benchmarks/bench_launch.py [--uavs 10 100 300] [--steps 20] [--out DIR]

Each point is paper-20uav's world (its targets and threats, random starts) with ``uavs.count``
changed. One ``swarmplan daemon --lockstep`` listens with one ``--connect
udpin:127.0.0.1:0@FIRST`` per 150 UAVs (a single one, without ``@``, up to 150), and as soon as
it says its ports, one ``swarmplan sim --lockstep --vehicles 150 --first-uav FIRST`` per network
sends there, each numbering its vehicles from system id 1: above 150 UAVs the daemon tells them
apart by (link, system id). It prints the wall time from the daemon's start to the end of each
phase of the launch (every vehicle heard; ready and airframes read; fence uploaded; GCS
failsafe set; armed; airborne) and to the first decision step, then the mission's steps,
violations and wall time (RTL is sent at the end; the flight home is not watched,
``--rtl-watch 0``). Real processes on loopback UDP; run it on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

PER_SIMULATOR = 150
#: what the daemon says at the end of each launch phase (mavlink_bridge/mission/launch.py)
PHASES = {
    "heard": "vehicles heard",
    "airframes": "airframe vehicle",
    "fence": "fence uploaded",
    "failsafe": "GCS failsafe set",
    "armed": "armed ",
    "airborne": "airborne",
}
STEP_LINE = re.compile(r"step\s+1\b|\b1/\d+")


def scenario_file(uavs: int, folder: Path) -> Path:
    """paper-20uav with ``uavs`` UAVs (random starts)."""
    text = (REPO / "planner" / "scenarios" / "paper-20uav.toml").read_text()
    text = text.replace('name = "paper-20uav"', f'name = "launch-{uavs}uav"')
    text = re.sub(r"count = \d+", f"count = {uavs}", text, count=1)
    path = folder / f"launch-{uavs}uav.toml"
    path.write_text(text)
    return path


def swarmplan(*args: str) -> list[str]:
    return [sys.executable, "-m", "swarmplan", *args]


def start_simulators(
    scenario: Path, uavs: int, ports: list[int], out: Path, telemetry_hz: float
) -> list:
    """One lockstep simulator per ``PER_SIMULATOR`` UAVs, sending to ``ports`` (in order)."""
    sims = []
    for k, port in enumerate(ports):
        first = k * PER_SIMULATOR
        count = min(PER_SIMULATOR, uavs - first)
        log = (out / f"sim{first}.log").open("w")  # (what it says: a lockstep released, ...)
        sims.append(
            subprocess.Popen(
                swarmplan("sim", "--scenario", str(scenario), "--seed", "1", "--lockstep",
                          "--quiet", "--vehicles", str(count), "--first-uav", str(first),
                          "--gcs-port", str(port), "--telemetry-hz", str(telemetry_hz)),
                stdout=log, stderr=subprocess.STDOUT, cwd=REPO,
            )
        )  # fmt: skip
    return sims


def fly(uavs: int, steps: int, out: Path, telemetry_hz: float) -> dict:
    """Start the daemon (on ports of its own choosing), then the simulators sending there; the
    wall time from the daemon's start to each launch phase, and the result."""
    scenario = scenario_file(uavs, out)
    firsts = list(range(0, uavs, PER_SIMULATOR))
    connect: list[str] = []
    for first in firsts:
        connect += ["--connect", "udpin:127.0.0.1:0" + (f"@{first}" if len(firsts) > 1 else "")]
    run_out = out / f"daemon-{uavs}"
    started = time.monotonic()
    daemon = subprocess.Popen(
        swarmplan("daemon", *connect, "--scenario", str(scenario), "--seed", "1",
                  "--steps", str(steps), "--lockstep", "--timeout", "120", "--no-view",
                  "--rtl-watch", "0", "--out", str(run_out)),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
    )  # fmt: skip
    times: dict[str, float] = {}
    log, sims = [], []
    try:
        assert daemon.stdout is not None
        for line in daemon.stdout:
            now = time.monotonic() - started
            log.append(f"{now:8.2f} {line}")
            if not sims and line.startswith("listening on "):
                ports = [int(p) for p in re.findall(r"udpin:127\.0\.0\.1:(\d+)", line)]
                sims = start_simulators(scenario, uavs, ports, out, telemetry_hz)
            for phase, says in PHASES.items():
                if says in line:
                    times[phase] = now  # (the last line of a phase: airframes say one each)
            if "first_step" not in times and "airborne" in times and STEP_LINE.search(line):
                times["first_step"] = now
        daemon.wait(timeout=60)
    finally:
        for sim in sims:
            sim.terminate()
        for sim in sims:
            try:
                sim.wait(timeout=10)
            except subprocess.TimeoutExpired:
                sim.kill()
    (out / f"daemon-{uavs}.log").write_text("".join(log))
    result_path = run_out / "result.json"
    result = json.loads(result_path.read_text()) if result_path.exists() else {}
    return {"uavs": uavs, "simulators": len(firsts), "times": times,
            "wall_s": time.monotonic() - started, "exit": daemon.returncode,
            "steps": result.get("steps"), "violations": result.get("violations"),
            "vehicles": len(result.get("uavs", []))}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--uavs", type=int, nargs="+", default=[10, 100, 300])
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_launch"))
    parser.add_argument(
        "--telemetry-hz",
        type=float,
        default=2.0,
        help="the simulators' position and attitude rate (default 2: at 10 Hz, 300 vehicles "
        "send the daemon ~9k messages a second)",
    )
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    names = ["heard", "airframes", "fence", "failsafe", "armed", "airborne", "first_step"]
    print(
        f"{'uavs':>5} {'sims':>4} "
        + " ".join(f"{n:>10}" for n in names)
        + "  steps  exit  violations"
    )
    for uavs in args.uavs:
        point = fly(uavs, args.steps, args.out, args.telemetry_hz)
        cells = " ".join(
            f"{point['times'][n]:>9.1f}s" if n in point["times"] else f"{'-':>10}" for n in names
        )
        print(
            f"{uavs:>5} {point['simulators']:>4} {cells}  {point['steps']!s:>5}  "
            f"{point['exit']!s:>4}"
            f"  {point['violations']}  (flew {point['vehicles']} vehicles,"
            f" {point['wall_s']:.0f} s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
