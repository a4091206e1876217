"""Vehicles told apart by (link, system id): two simulators whose vehicles have the SAME system
ids 1..3, each sending to its own port, flown by one daemon (``--connect ENDPOINT@FIRST``,
mavlink_bridge/vehicles/vehicle_key.py). Real UDP on loopback, real processes, lockstep."""

from __future__ import annotations

import json
import math

import pytest
from loopback import free_udp_port, run_swarmplan, start_swarmplan, stop

from planner.scenario import load_scenario

SCENARIO, SEED, PER_SIM, STEPS = "paper-10uav", "1", 3, 6


@pytest.mark.timeout(150)
def test_two_simulators_with_the_same_system_ids(tmp_path):
    ports = [free_udp_port(), free_udp_port()]
    sims = []
    try:
        for k, port in enumerate(ports):
            sims.append(
                start_swarmplan(
                    ["sim", "--scenario", SCENARIO, "--seed", SEED, "--lockstep", "--quiet",
                     "--vehicles", str(PER_SIM), "--first-uav", str(k * PER_SIM),
                     "--gcs-port", str(port)],
                    tmp_path / f"sim{k}.log",
                )
            )  # fmt: skip
        connect = []
        for k, port in enumerate(ports):  # network k + 1 serves UAVs from k * PER_SIM
            connect += ["--connect", f"udpin:127.0.0.1:{port}@{k * PER_SIM}"]
        proc = run_swarmplan(
            ["daemon", *connect, "--scenario", SCENARIO, "--seed", SEED,
             "--expect", str(2 * PER_SIM), "--steps", str(STEPS), "--lockstep", "--timeout",
             "30", "--json", "--out", str(tmp_path / "out")],
            timeout=120,
        )  # fmt: skip
    finally:
        for sim in sims:
            stop(sim)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout)
    assert result["steps"] == STEPS and len(result["uavs"]) == 2 * PER_SIM
    # told apart: each network's system ids 1..3, named LINK:SYSID
    assert result["vehicles"] == [f"{link}:{s}" for link in (1, 2) for s in (1, 2, 3)]
    assert all(u["distance_km"] > 4 for u in result["uavs"])  # all six flew
    # each UAV's track is its own vehicle's: it begins at that UAV's start in the scenario
    starts = load_scenario(SCENARIO).starts_for_seed(int(SEED))
    for uav, start in zip(result["uavs"], starts, strict=False):
        x, y = uav["track_km"][0]
        assert math.hypot(x - start.x_km, y - start.y_km) < 1.5, (uav["id"], (x, y), start)
    assert sorted(result["rtl_sent_to"]) == sorted(result["vehicles"])
