"""The onboard swarm on real autopilots (``ARDUPLANE_SITL``; docs/onboard.md, "On a companion
computer"): three ArduPlane SITL planes at 10x, each flown by its OWN ``swarmplan node`` on its
autopilot's SERIAL2 (TCP 5763 + 10 N, a companion computer's place), the payload simulator on
each SERIAL1, and ``swarmplan radio-relay`` between their SERIAL0 ports as the planes' radio
(range and loss from the planes' own positions). No ground station: the nodes launch, search,
hear each other through autopilot -> relay -> autopilot, bring the planes home, and their parts
are joined by ``swarmplan demo --onboard --join``. Every process runs in a session of its own
and is stopped by process group."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from loopback import env
from sitl_harness import SitlSwarm, _listening, homes_for_scenario
from sitl_mission import turn_breaks_by_step_length

from planner.scenario import load_scenario

REPO = Path(__file__).resolve().parents[2]
SCENARIO = "arduplane-3uav"
#: six steps: seed 1 flown offline as the daemon plans it (``swarmplan run arduplane-3uav
#: --as-flown --steps 6``) engages target 1 at step 4; four steps engaged in 1 of 2 SITL runs
STEPS = 6
SPEEDUP = 10.0
RANGE_KM, LOSS = 10.0, 0.1
NODES_TIMEOUT_S = 150.0
#: node i's own MAVLink system id, which its plane's MAV_GCS_SYSID names
NODE_SYSTEM_BASE = 201


def _start(args: list[str], log: Path) -> subprocess.Popen:
    """``python -m swarmplan ARGS`` in a session (process group) of its own, output to ``log``."""
    with open(log, "wb") as sink:
        return subprocess.Popen(
            [sys.executable, "-m", "swarmplan", *args], stdout=sink, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, env=env(PYTHONUNBUFFERED="1"), cwd=REPO,
            start_new_session=True,
        )  # fmt: skip


def _stop(proc: subprocess.Popen, grace_s: float = 10.0) -> None:
    """SIGTERM to its process group, SIGKILL after ``grace_s``."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        if proc.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(grace_s)


def _last_json(path: Path) -> dict | None:
    lines = path.read_text(errors="replace").splitlines() if path.is_file() else []
    return next((json.loads(line) for line in reversed(lines) if line.startswith("{")), None)


def _explain(out: Path) -> str:
    logs = sorted(out.glob("node-*/node.log")) + [out / "radio-relay.log", out / "payload.log"]
    return "\n".join(
        f"--- {p.relative_to(out)}\n" + "\n".join(p.read_text(errors="replace").splitlines()[-12:])
        for p in logs
        if p.is_file()
    )


def fly_nodes(binary: Path, workdir: Path) -> tuple[Path, list[int | None], float]:
    """The whole onboard mission (module docstring): the result folder, the nodes' exit
    statuses and the wall time from the first SITL's start to the last node's end."""
    scenario = load_scenario(SCENARIO)
    out = workdir / "out"
    out.mkdir(parents=True)
    procs: list[subprocess.Popen] = []
    started = time.monotonic()
    with SitlSwarm(
        binary, homes_for_scenario(scenario, 1), speedup=SPEEDUP,
        params={"FENCE_ENABLE": 1, "SERIAL2_PROTOCOL": 2}, workdir=workdir / "sitl",
        vehicle_params=lambda i: {"MAV_GCS_SYSID": NODE_SYSTEM_BASE + i},
    ) as swarm:  # fmt: skip
        try:
            # the radio first: ArduPlane SITL boots once its SERIAL0 has a client
            relay = _start(
                ["radio-relay", "--radio-range-km", f"{RANGE_KM:g}", "--radio-loss", f"{LOSS:g}",
                 "--seed", "1", *(a for v in swarm.vehicles for a in ("--connect", v.master))],
                out / "radio-relay.log",
            )  # fmt: skip
            procs.append(relay)
            deadline = time.monotonic() + 30
            for v in swarm.vehicles:
                while not _listening(v.port + 3):
                    assert time.monotonic() < deadline, f"SERIAL2 of vehicle {v.system_id} shut"
                    assert relay.poll() is None, _explain(out)
                    time.sleep(0.1)
            procs.append(_start(
                ["payload", "--scenario", SCENARIO, "--seed", "1", *swarm.payload_args()],
                out / "payload.log",
            ))  # fmt: skip
            nodes = []
            for v in swarm.vehicles:
                folder = out / f"node-{v.index}"
                folder.mkdir()
                nodes.append(_start(
                    ["node", SCENARIO, "--uav", str(v.index), "--connect",
                     f"tcp:127.0.0.1:{v.port + 3}", "--seed", "1", "--steps", str(STEPS),
                     "--time-scale", f"{SPEEDUP:g}", "--system-id", str(NODE_SYSTEM_BASE + v.index),
                     "--out", str(folder)],
                    folder / "node.log",
                ))  # fmt: skip
            procs += nodes
            deadline = time.monotonic() + NODES_TIMEOUT_S
            while any(n.poll() is None for n in nodes) and time.monotonic() < deadline:
                time.sleep(0.5)
            wall_s = time.monotonic() - started
            codes = [n.poll() for n in nodes]
        finally:
            for proc in reversed(procs):  # the relay last: it says its count at its end
                _stop(proc)
    return out, codes, wall_s


@pytest.mark.timeout(240)
def test_three_nodes_fly_their_own_arduplanes_through_a_radio_relay(sitl_binary, tmp_path):
    out, codes, wall_s = fly_nodes(sitl_binary, tmp_path)
    print(f"3 nodes on ArduPlane SITL at {SPEEDUP:g}x, {STEPS} steps: {wall_s:.1f} s wall")
    assert codes == [0, 0, 0], _explain(out)
    relay, payload = _last_json(out / "radio-relay.log"), _last_json(out / "payload.log")
    assert relay is not None and payload is not None, _explain(out)
    # every plane's camera looked at each step (the payload simulator on SERIAL1 -> its node)
    assert all(n >= STEPS for n in payload["looks_per_vehicle"]), payload
    # each node launched and flew its own plane, and wrote its part
    for i in range(3):
        log = (out / f"node-{i}" / "node.log").read_text()
        assert f"node {i}: airborne, GUIDED" in log, log
        part = json.loads((out / f"node-{i}" / "result.json").read_text())
        assert part["architecture"] == "onboard" and part["uav"] == i
        assert part["steps"] == STEPS, part.get("ended")
        # it heard its neighbours: autopilot -> relay -> the other autopilot -> its node
        assert part["link"]["reports_heard"] > 0, part["link"]
        # safety along every position report of its plane (the flight home included); the
        # turn rule as the daemon's SITL test counts it (tests/sitl/test_sitl_mission.py): on
        # the regular steps the plan did not ask for, at most one (a machine that stalls the
        # autopilots leaves a plane circling; one run of the 255-identity variant had one)
        audit = part["track_audit"]["all"]
        assert audit["threat_entries"] == 0 and audit["separation_breaches"] == 0, audit
        v = part["violations"]
        assert (v["threat"], v["separation"], v["range"]) == (0, 0, 0), v
        step_s = load_scenario(SCENARIO).config.step_s
        assert turn_breaks_by_step_length(part, step_s)["turn_breaks_regular_steps"] <= 1, v
        # its plane sent home
        home = set(part["rtl_sent_to"]) | set(part.get("guided_home_around_threats", []))
        assert home == {i + 1}, part.get("rtl_not_sent")
    # the radio carried the swarm link and nothing else: no node's or plane's heartbeat crossed
    assert relay["planes"] == [1, 2, 3], relay
    assert relay["delivered"] > 0 and relay["lost_to_loss"] > 0, relay
    assert relay["not_relayed"].get("HEARTBEAT", 0) > 0, relay
    assert relay["min_separation_km"] >= 1.0, relay  # the scenario's d_min: what really flew
    # the coordinator's join of the parts (no ground station took part in the flight)
    joined = subprocess.run(
        [sys.executable, "-m", "swarmplan", "demo", SCENARIO, "--onboard", "--join", "--seed", "1",
         "--out", str(out)],
        capture_output=True, text=True, timeout=60, env=env(), cwd=REPO,
    )  # fmt: skip
    assert joined.returncode == 0, joined.stdout + joined.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["nodes_missing"] == [] and result["steps"] == STEPS
    assert result["coverage"] > 0
    # at least one engagement, the nodes' and the world's alike
    engaged = sorted(e["target_id"] for e in result["engagements"])
    assert engaged and engaged == payload["targets_engaged"], (engaged, payload)
    v = result["violations"]
    assert (v["threat"], v["separation"], v["range"]) == (0, 0, 0), v
    assert result["link"]["radio"]["delivered"] == relay["delivered"]
    print(joined.stdout)
