"""Missions against the real PX4 SITL (``PX4_SITL``: PX4's built-in SIH airplane), with real
processes only: PX4 instances (tests/sitl/px4_harness.py), ``swarmplan payload`` on their
onboard links (PX4 forwards the camera, component 100, to the GCS link) and ``swarmplan
daemon`` on their GCS links.

* Two PX4 planes at real time (1x) become ready (PX4's pre-arm bit), arm, take off (runway,
  NAV_TAKEOFF), fly two decision steps guided in AUTO.LOITER, look and engage through PX4's
  forwarding, and are sent home (RTL), with no violation (~4 min wall on a loaded machine).
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from loopback import env, stop
from px4_harness import Px4Swarm
from sitl_harness import homes_for_scenario

from planner.scenario import load_scenario

REPO = Path(__file__).resolve().parents[2]


def fly_px4(root: Path, workdir: Path, scenario: str, steps: int, speedup: float, timeout_s: float):
    """One mission against PX4 instances at the scenario's starts; (exit, daemon output,
    result.json or None, payload output). Every process is stopped on the way out."""
    loaded = load_scenario(scenario)
    out = workdir / "out"
    lines: list[str] = []
    run = [sys.executable, "-m", "swarmplan"]
    with Px4Swarm(root, homes_for_scenario(loaded, 1), speedup=speedup,
                  workdir=workdir / "px4") as swarm:  # fmt: skip
        payload = subprocess.Popen(
            [*run, "payload", "--scenario", scenario, *swarm.payload_args()],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env(),
            cwd=REPO,
        )  # fmt: skip
        daemon = subprocess.Popen(
            [*run, "daemon", "--scenario", scenario, "--time-scale", f"{speedup:g}",
             "--out", str(out), "--no-view", "--steps", str(steps), *swarm.connect_args()],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            env=env(PYTHONUNBUFFERED="1"), cwd=REPO,
        )  # fmt: skip
        reader = threading.Thread(target=lambda: lines.extend(daemon.stdout), daemon=True)
        reader.start()
        try:
            code = daemon.wait(timeout_s)
        except subprocess.TimeoutExpired:
            code = None
        finally:
            stop(daemon, 10.0)
            stop(payload, 10.0)
        reader.join(5)
        payload_text = payload.stdout.read() if payload.stdout else ""
    result = out / "result.json"
    return (
        code,
        "".join(lines),
        json.loads(result.read_text()) if result.is_file() else None,
        (payload_text),
    )


@pytest.mark.timeout(420)
def test_two_px4_planes_at_real_time_arm_take_off_fly_two_steps_and_engage(px4_sitl, tmp_path):
    scenario = str(Path(__file__).with_name("px4-1x.toml"))
    started = time.monotonic()
    code, text, result, payload = fly_px4(px4_sitl, tmp_path, scenario, 2, 1.0, 360)
    wall = time.monotonic() - started
    explain = f"exit {code} after {wall:.0f} s:\n{text[-4000:]}\n{payload[-800:]}"
    assert code == 0, explain
    # PX4's own settings, never ArduPilot's (FS_SHORT_ACTN was refused before)
    assert "GCS failsafe set: NAV_DLL_ACT 0" in text and "FS_" not in text, explain
    assert "armed 2 vehicles after" in text and "airborne, AUTO.LOITER" in text, explain
    assert result is not None and result["steps"] == 2, explain
    # the cameras on PX4's other link were heard through its forwarding, and engaged
    assert result["uavs_without_camera"] == [], explain
    assert result["engaged_count"] >= 1, explain
    v = result["violations"]
    assert (v["threat"], v["separation"], v["range"]) == (0, 0, 0), explain
    assert sorted(result["rtl_sent_to"]) == [1, 2], explain
