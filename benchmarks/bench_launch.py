"""How long the daemon's launch takes against the swarm's size, and a swarm of more than one
MAVLink network flown end to end.

    python benchmarks/bench_launch.py [--uavs 10 100 300] [--steps 20] [--out DIR]

Each point is paper-20uav's world (its targets and threats, random starts) with ``uavs.count``
changed, flown by ``swarmplan sim --lockstep`` (one simulator per 150 vehicles, each sending to
its own UDP port as system ids 1..150, ``--first-uav``) and one ``swarmplan daemon --lockstep``
with one ``--connect udpin:127.0.0.1:PORT@FIRST`` per simulator (vehicles told apart by
(link, system id); a single simulator is one network, as always). It prints the wall time from
the daemon's start to each phase of the launch (every vehicle heard, ready and airframes read,
fence uploaded, GCS failsafe set, armed, airborne) and to the first decision step, then the
mission's steps, violations and wall time. Points above 150 vehicles are the >255-vehicle case
in small: two simulators whose vehicles share system ids. Real processes on loopback UDP; run it
on an idle machine (``nice`` the rest): the launch is mostly waiting on the simulators' clocks.
"""

from __future__ import annotations

import argparse
import json
import re
import socket
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


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def swarmplan(*args: str) -> list[str]:
    return ["nice", "-n", "5", sys.executable, "-m", "swarmplan", *args]


def fly(uavs: int, steps: int, out: Path) -> dict:
    """Start the simulators and the daemon; the wall time of each launch phase and the result."""
    scenario = scenario_file(uavs, out)
    firsts = list(range(0, uavs, PER_SIMULATOR))
    ports = [free_port() for _ in firsts]
    sims = []
    connect: list[str] = []
    for first, port in zip(firsts, ports, strict=True):
        count = min(PER_SIMULATOR, uavs - first)
        sims.append(
            subprocess.Popen(
                swarmplan("sim", "--scenario", str(scenario), "--seed", "1", "--lockstep",
                          "--quiet", "--vehicles", str(count), "--first-uav", str(first),
                          "--gcs-port", str(port)),
                stdout=subprocess.DEVNULL, stderr=(out / f"sim{first}.log").open("w"), cwd=REPO,
            )
        )  # fmt: skip
        connect += [
            "--connect",
            f"udpin:127.0.0.1:{port}" + (f"@{first}" if len(firsts) > 1 else ""),
        ]
    run_out = out / f"daemon-{uavs}"
    started = time.monotonic()
    daemon = subprocess.Popen(
        swarmplan("daemon", *connect, "--scenario", str(scenario), "--seed", "1",
                  "--steps", str(steps), "--lockstep", "--timeout", "120", "--no-view",
                  "--rtl-watch", "0", "--out", str(run_out)),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
    )  # fmt: skip
    times: dict[str, float] = {}
    log = []
    try:
        assert daemon.stdout is not None
        for line in daemon.stdout:
            now = time.monotonic() - started
            log.append(f"{now:8.2f} {line}")
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
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    names = ["heard", "airframes", "fence", "failsafe", "armed", "airborne", "first_step"]
    print(
        f"{'uavs':>5} {'sims':>4} "
        + " ".join(f"{n:>10}" for n in names)
        + "  steps  exit  violations"
    )
    for uavs in args.uavs:
        point = fly(uavs, args.steps, args.out)
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
