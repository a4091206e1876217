"""Waypoint export: QGC WPL 110 read by pymavlink's mavwp and loaded by MAVProxy, a
QGroundControl .plan of the right structure, GeoJSON and KML of tracks and threat zones."""

from __future__ import annotations

import json
import shutil
import subprocess
import time
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from loopback import run_swarmplan

from mavlink_bridge.export.waypoint_export import (
    export_all,
    simplify_path,
)
from planner.errors import UserError
from planner.metrics import MissionRecorder
from swarmplan.export_command import load_result


@pytest.fixture
def result(paper10) -> dict:
    """A small two-UAV result made by the real recorder: out east / north and back."""
    starts = paper10.starts_for_seed(1)[:2]
    recorder = MissionRecorder(paper10, starts)
    pos = np.array([[s.x_km, s.y_km] for s in starts])
    for k in range(12):
        nxt = pos + np.array([[1.0, 0.0], [0.0, 1.0]]) * (1 if k < 6 else -1)
        recorder.record_step(pos, planned_km=nxt)
        pos = nxt
    return recorder.result(1, "hapf-aco", 0.1)


def test_export_all_writes_every_format(result, tmp_path):
    files = export_all(result, tmp_path)
    names = {p.relative_to(tmp_path).as_posix() for p in files}
    assert {
        "waypoints/uav01_planned.waypoints",
        "waypoints/uav02_flown.waypoints",
        "plan/uav01.plan",
        "mission.geojson",
        "mission.kml",
    } <= names


def test_wpl_has_twelve_columns_and_home_first(result, tmp_path):
    export_all(result, tmp_path)
    lines = (tmp_path / "waypoints/uav01_planned.waypoints").read_text().splitlines()
    assert lines[0] == "QGC WPL 110"
    rows = [line.split("\t") for line in lines[1:]]
    assert all(len(r) == 12 for r in rows)
    assert [int(r[0]) for r in rows] == list(range(len(rows)))
    assert rows[0][1] == "1" and rows[1][3] == "22" and rows[-1][3] == "20"  # home, takeoff, RTL
    # the straight run out and back collapses to its corners: home, takeoff, 2-3 turns, RTL
    assert len(rows) <= 6


def test_mavwp_loader_reads_the_wpl(result, tmp_path):
    from pymavlink import mavwp

    export_all(result, tmp_path)
    loader = mavwp.MAVWPLoader()
    count = loader.load(str(tmp_path / "waypoints/uav02_planned.waypoints"))
    assert count == loader.count() >= 4
    home = loader.wp(0)
    assert home.command == 16 and home.frame == 0
    lat0 = result["origin"]["lat"]
    assert all(abs(loader.wp(i).x - lat0) < 1.5 for i in range(count - 1))


def test_qgc_plan_structure(result, tmp_path):
    export_all(result, tmp_path)
    plan = json.loads((tmp_path / "plan/uav01.plan").read_text())
    assert plan["fileType"] == "Plan" and plan["version"] == 1
    mission = plan["mission"]
    assert mission["version"] == 2 and mission["firmwareType"] == 3 and mission["vehicleType"] == 1
    assert {"cruiseSpeed", "hoverSpeed", "plannedHomePosition", "items"} <= set(mission)
    assert len(mission["plannedHomePosition"]) == 3
    for item in mission["items"]:
        assert item["type"] == "SimpleItem" and len(item["params"]) == 7
        assert {"command", "frame", "autoContinue", "doJumpId"} <= set(item)
    fence = plan["geoFence"]
    assert fence["version"] == 2 and len(fence["circles"]) == len(result["threats"])
    for c in fence["circles"]:
        assert c["inclusion"] is False and c["version"] == 1
        assert len(c["circle"]["center"]) == 2 and c["circle"]["radius"] > 0
    assert plan["rallyPoints"] == {"points": [], "version": 2}


def test_geojson_and_kml(result, tmp_path):
    export_all(result, tmp_path)
    doc = json.loads((tmp_path / "mission.geojson").read_text())
    kinds = [f["geometry"]["type"] for f in doc["features"]]
    assert kinds.count("LineString") == 4 and kinds.count("Polygon") == len(result["threats"])
    ring = next(f for f in doc["features"] if f["geometry"]["type"] == "Polygon")["geometry"][
        "coordinates"
    ][0]
    assert ring[0] == ring[-1]
    tree = ET.parse(tmp_path / "mission.kml")
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    assert len(tree.findall(".//k:Placemark", ns)) == 4 + len(result["threats"])


def test_simplify_keeps_turns():
    path = np.array([[0, 0], [1, 0], [2, 0], [3, 1], [4, 2], [4, 2], [4, 3]], float)
    assert simplify_path(path).tolist() == [[0, 0], [2, 0], [4, 2], [4, 3]]


def test_export_command_errors_are_one_line(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        load_result(tmp_path)
    (tmp_path / "result.json").write_text("{not json")
    with pytest.raises(UserError, match="not valid JSON"):
        load_result(tmp_path)


def test_export_command_cli(result, tmp_path):
    (tmp_path / "result.json").write_text(json.dumps(result))
    proc = run_swarmplan(["export", str(tmp_path), "--format", "wpl"], timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "uav01_planned.waypoints" in proc.stdout
    assert not (tmp_path / "mission.kml").exists()


@pytest.mark.skipif(shutil.which("mavproxy.py") is None, reason="MAVProxy not installed")
def test_mavproxy_wp_load(result, tmp_path, udp_port, fake_swarm_factory):
    """MAVProxy (a real client) loads the exported file and uploads it to a vehicle."""
    export_all(result, tmp_path)
    wpl = tmp_path / "waypoints/uav01_planned.waypoints"
    expected = len(wpl.read_text().splitlines()) - 1
    swarm = fake_swarm_factory(1, udp_port)
    proc = subprocess.Popen(
        [
            shutil.which("mavproxy.py"),
            f"--master=udpin:127.0.0.1:{udp_port}",
            "--no-state",
            "--default-modules=wp,cmdlong",
            "--state-basedir",
            str(tmp_path),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=tmp_path,
    )
    try:
        time.sleep(3)
        assert proc.stdin is not None
        proc.stdin.write(f"wp load {wpl}\n")
        proc.stdin.flush()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and len(swarm.vehicles[0].mission_items) < expected:
            time.sleep(0.2)
        proc.stdin.write("exit\n")
        proc.stdin.flush()
    finally:
        proc.terminate()
        try:
            out, _ = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
    assert f"Loaded {expected} waypoints" in out, out[-2000:]
    items = swarm.vehicles[0].mission_items
    assert len(items) == expected
    assert [i.command for i in items][:2] == [16, 22]
