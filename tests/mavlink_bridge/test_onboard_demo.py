"""The swarm without a centre end to end (``swarmplan demo --onboard``): the simulator, one
``swarmplan node`` process per UAV and the coordinator, on loopback UDP with free ports. Three
UAVs of paper-10uav, a few steps at 10x: the planes come home with zero violations (the
simulator's truth) and the result has the link's figures; the coordinator killed mid-mission,
the nodes fly on, bring the planes home and each writes its part."""

from __future__ import annotations

import json
import os
import re
import signal
import time
from pathlib import Path

import loopback
import pytest
from onboard_processes import end_processes, is_running, onboard_pids

from planner.scenario import load_scenario

BUDGET_BYTES = 3600  # the swarm link's budget per UAV per step (docs/onboard.md)
STEPS = 4


def _scenario(tmp_path: Path, uavs: int) -> Path:
    """paper-10uav with fewer UAVs (a few processes on the CI's two cores)."""
    text = (Path(loopback.REPO) / "planner/scenarios/paper-10uav.toml").read_text()
    path = tmp_path / f"paper-{uavs}uav-onboard.toml"
    path.write_text(text.replace("count = 10", f"count = {uavs}"))
    assert load_scenario(path).uav_count == uavs
    return path


def _sim_truth(sim_log: Path) -> dict:
    lines = [x for x in sim_log.read_text().splitlines() if x.startswith("{")]
    return json.loads(lines[-1])["safety"]


def _demo(scenario: Path, out: Path, log: Path):
    args = ["demo", str(scenario), "--seed", "2", "--onboard", "--steps", str(STEPS),
            "--speedup", "10", "--radio-range-km", "60", "--out", str(out), "--json"]  # fmt: skip
    return loopback.start_swarmplan(args, log, stdout_pipe=True)


@pytest.mark.timeout(240)
def test_an_onboard_demo_brings_the_planes_home_with_the_link_figures(tmp_path):
    out, log = tmp_path / "run", tmp_path / "coordinator.log"
    coordinator = _demo(_scenario(tmp_path, 3), out, log)
    pids: list[int] = []
    try:
        pids = onboard_pids(log, coordinator)
        stdout, _ = coordinator.communicate(timeout=200)
    finally:
        loopback.stop(coordinator)
        end_processes(pids)
    assert coordinator.returncode == 0, log.read_text()[-3000:]
    result = json.loads(stdout)
    assert result == json.loads((out / "result.json").read_text())
    assert result["architecture"] == "onboard" and result["nodes_missing"] == []
    assert result["steps"] == STEPS
    assert result["returned_count"] == 3
    assert set(result["violations"].values()) == {0}
    truth = result["simulator_truth"]
    assert truth["threat_entries"] == 0 and truth["separation_breaches"] == 0
    link = result["link"]
    assert 0 < link["bytes_sent_per_uav_per_step"]["mean"] <= link[
        "bytes_sent_per_uav_per_step"]["max"] <= BUDGET_BYTES  # fmt: skip
    assert link["radio"]["frames_sent"] > 0 and link["radio"]["delivered"] > 0
    for node in link["nodes"].values():
        assert node["reports_heard"] > 0 and len(node["bytes_sent"]) == STEPS + 1


@pytest.mark.timeout(240)
def test_the_nodes_fly_on_and_home_when_the_coordinator_is_killed(tmp_path):
    out, log = tmp_path / "run", tmp_path / "coordinator.log"
    scenario = _scenario(tmp_path, 2)
    coordinator = _demo(scenario, out, log)
    pids: list[int] = []
    try:
        pids = onboard_pids(log, coordinator)
        deadline = time.monotonic() + 150
        while not re.search(r"step\s+1/", (out / "node-0" / "node.log").read_text(
                errors="replace")):  # fmt: skip
            assert time.monotonic() < deadline and coordinator.poll() is None
            time.sleep(0.2)
        coordinator.kill()  # mid-mission, without a word to anyone
        coordinator.wait(10)
        sim, nodes = pids[0], pids[1:]
        while any(is_running(p) for p in nodes):  # the nodes fly on to their end
            assert time.monotonic() < deadline + 60, "the nodes did not finish"
            time.sleep(0.5)
        assert is_running(sim)  # the world did not stop with the coordinator
        os.kill(sim, signal.SIGTERM)
        while is_running(sim) and time.monotonic() < deadline + 80:
            time.sleep(0.2)
    finally:
        loopback.stop(coordinator)
        end_processes(pids)
    assert not (out / "result.json").exists()  # the coordinator never joined
    for i in range(2):
        part = json.loads((out / f"node-{i}" / "result.json").read_text())
        assert part["ended"] == "completed" and part["steps"] == STEPS
        assert part["returned_count"] == 1 and set(part["violations"].values()) == {0}
        assert part["link"]["reports_heard"] > 0
    truth = _sim_truth(out / "sim.log")
    assert truth["threat_entries"] == 0 and truth["separation_breaches"] == 0
    # the parts joined afterwards, as the coordinator would have
    joined = loopback.run_swarmplan(["demo", str(scenario), "--seed", "2", "--onboard", "--join",
                                     "--out", str(out), "--json"], timeout=120)  # fmt: skip
    assert joined.returncode == 0, joined.stderr
    result = json.loads(joined.stdout)
    assert result["returned_count"] == 2 and result["nodes_missing"] == []
    assert result["simulator_truth"] == truth and result["link"]["radio"]["delivered"] > 0
