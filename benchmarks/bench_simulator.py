"""Benchmark of the MAVLink simulator (sim_gateway): how many vehicles one core keeps in real
time with 10 Hz telemetry, and the speedup reached with 10 and 20 vehicles.

    python benchmarks/bench_simulator.py [--seconds 4]

Vehicles start airborne in LOITER (every stream on, kinematics and looks running) and send to a
local UDP sink that nobody reads (the kernel drops what overflows: the cost measured is the
simulator's own). CPU load = process CPU time / wall time of a real-time run; the real-time
capacity is the largest count whose load stays under 100 %, extrapolated linearly from the runs.
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import time
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from planner.scenario import load_scenario  # noqa: E402
from sim_gateway.simulator import SimOptions, Simulator  # noqa: E402


def sink() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    return s


def realtime_load(n: int, seconds: float, port: int) -> tuple[float, float, float]:
    """(CPU load, lag in simulated s, messages sent per s) of ``n`` vehicles in real time."""
    opts = SimOptions(vehicles=n, airborne=True, gcs_port=port, position_rate_hz=10.0)
    with Simulator(load_scenario("paper-10uav"), opts) as sim:
        sim.run(sim_duration_s=0.5)  # warm up
        cpu0, wall0, sim0, sent0 = (
            time.process_time(),
            time.monotonic(),
            sim.sim_time_s,
            sim.stats.sent,
        )
        sim.run(wall_limit_s=seconds)
        cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
        lag = wall - (sim.sim_time_s - sim0)
        return cpu / wall, lag, (sim.stats.sent - sent0) / wall


def fast_speedup(n: int, sim_seconds: float, port: int) -> tuple[float, int]:
    opts = SimOptions(vehicles=n, airborne=True, fast=True, gcs_port=port, position_rate_hz=10.0)
    with Simulator(load_scenario("paper-20uav"), opts) as sim:
        wall0 = time.monotonic()
        sim.run(sim_duration_s=sim_seconds)
        wall = time.monotonic() - wall0
        return sim_seconds / wall, sim.stats.sent


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=4.0, help="wall seconds per real-time run")
    parser.add_argument(
        "--sim-seconds", type=float, default=1200.0, help="simulated s per fast run"
    )
    args = parser.parse_args()
    s = sink()
    port = s.getsockname()[1]
    print("sim_gateway benchmark (one process, one core; telemetry 10 Hz position + attitude)")
    loads = []
    for n in (25, 50, 100, 200):
        load, lag, rate = realtime_load(n, args.seconds, port)
        loads.append((n, load))
        print(
            f"  real time, {n:4d} vehicles: CPU load {load * 100:5.1f} %, lag {lag:+.2f} s, "
            f"{rate:7.0f} messages/s"
        )
    per_vehicle = max(load / n for n, load in loads[-2:])
    print(
        f"  => real-time capacity ~ {int(1.0 / per_vehicle)} vehicles per core at 10 Hz telemetry "
        f"(extrapolated; one simulator serves at most 200 system ids)"
    )
    for n in (10, 20):
        speedup, sent = fast_speedup(n, args.sim_seconds, port)
        print(f"  fast mode, {n:4d} vehicles: {speedup:7.1f}x real time ({sent} messages sent)")
    s.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
