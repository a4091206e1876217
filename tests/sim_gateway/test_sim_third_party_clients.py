"""Real third-party clients from PyPI drive the simulator over loopback UDP: MAVProxy (as a
subprocess fed commands on stdin, the simulator also a subprocess started by the command line)
and MAVSDK-Python 4.x (in process, its bundled C library)."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
from loopback import env, free_udp_port, start_swarmplan, stop


def _require(module: str, pip_command: str):
    """The client, or a skip (a failure under CI, which must have it installed)."""
    try:
        return __import__(module)
    except ImportError:
        if os.environ.get("CI"):
            pytest.fail(f"{module} is not installed; CI must run: {pip_command}")
        pytest.skip(f"{module} not installed ({pip_command})")


WAYPOINTS = """QGC WPL 110
0\t1\t0\t16\t0\t0\t0\t0\t-35.263000\t149.275000\t584.000000\t1
1\t0\t3\t22\t0\t0\t0\t0\t0\t0\t120.000000\t1
2\t0\t3\t16\t0\t0\t0\t0\t-35.250000\t149.290000\t150.000000\t1
3\t0\t3\t16\t0\t0\t0\t0\t-35.240000\t149.270000\t150.000000\t1
"""


def test_mavproxy_sees_every_vehicle_changes_mode_and_flies_a_wpl_mission(tmp_path):
    _require("MAVProxy", "pip install --no-deps mavproxy==1.8.75")
    port = free_udp_port()
    wp_file = tmp_path / "mission.txt"
    wp_file.write_text(WAYPOINTS)
    sim_log = tmp_path / "sim.log"
    sim = start_swarmplan(
        ["sim", "--scenario", "paper-2uav", "--gcs-port", str(port), "--boot-s", "2",
         "--speedup", "10", "--quiet"],
        sim_log,
    )  # fmt: skip
    mavproxy = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "MAVProxy.mavproxy",
            f"--master=udpin:127.0.0.1:{port}",
            "--no-state",
            "--default-modules=link,wp,fence,param,cmdlong,mode,arm,misc,ftp",
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env(),
        cwd=tmp_path,
    )
    output: list[str] = []
    reader = threading.Thread(
        target=lambda: output.extend(iter(mavproxy.stdout.readline, "")), daemon=True
    )
    reader.start()

    def wait_for(text: str, timeout: float = 20.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(text in line for line in output):
                return True
            time.sleep(0.1)
        return False

    def send(command: str) -> None:
        mavproxy.stdin.write(command + "\n")
        mavproxy.stdin.flush()

    try:
        assert wait_for("Detected vehicle 1:1") and wait_for("Detected vehicle 2:1"), output
        assert wait_for("Received 22 parameters"), output  # MAVFTP refused, fell back to PARAM_*
        send("vehicle 2")
        send("mode LOITER")
        assert wait_for("DO_SET_MODE: ACCEPTED"), output
        send(f"wp load {wp_file}")
        assert wait_for("Got MISSION_ACK: TYPE_MISSION: ACCEPTED"), output
        send("arm throttle")
        assert wait_for("COMPONENT_ARM_DISARM: ACCEPTED"), output
        send("mode AUTO")
        assert wait_for("Mode AUTO"), output
        assert wait_for("waypoint 2", timeout=30), output  # took off (item 1 done), flying to 2
    finally:
        send("exit")
        stop(mavproxy, sig=signal.SIGINT)
        stop(sim, sig=signal.SIGINT)
    sim_out = sim_log.read_text(errors="replace")
    assert "Traceback" not in sim_out, sim_out


def test_mavsdk_connects_reads_position_uploads_a_mission_arms_and_starts_it(gcs_free_sim):
    mavsdk = _require("mavsdk", "pip install -e .[test]")
    assert mavsdk.__version__.startswith("4.")
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.mission_raw import MissionRawAsync
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
    from mavsdk.plugins.mission_raw import MissionItem

    port, sim = gcs_free_sim
    lat, lon = sim.local_to_geodetic(14_000.0, 14_000.0)

    async def session() -> tuple[float, int, int, int]:
        config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
        async with Mavsdk(config) as drone:
            await drone.add_any_connection(f"udpin://127.0.0.1:{port}")
            system = await drone.first_autopilot(timeout_s=10.0)
            assert system is not None
            telemetry = TelemetryAsync(system)
            async for position in telemetry.subscribe_position():  # noqa: B007
                break
            items = [
                MissionItem(0, 0, 16, 1, 1, 0, 0, 0, 0, round(lat * 1e7), round(lon * 1e7), 584, 0),
                MissionItem(1, 3, 22, 0, 1, 0, 0, 0, 0, 0, 0, 100, 0),
                MissionItem(2, 6, 16, 0, 1, 0, 0, 0, 0, round(lat * 1e7), round(lon * 1e7), 150, 0),
            ]
            mission = MissionRawAsync(system)
            await mission.upload_mission(items)
            downloaded = await mission.download_mission()
            await ActionAsync(system).arm()
            await mission.start_mission()
            async for progress in mission.subscribe_mission_progress():
                if progress.current >= 1:
                    break
            return position.latitude_deg, len(downloaded), progress.current, progress.total

    lat_seen, n_items, current, total = asyncio.run(asyncio.wait_for(session(), 60))
    assert (
        abs(lat_seen - sim.local_to_geodetic(sim.vehicles[0].home_x_m, sim.vehicles[0].home_y_m)[0])
        < 0.5
    )
    assert n_items == 3 and current >= 1 and total >= 2
    assert any(v.armed and v.mode == 10 for v in sim.vehicles)


@pytest.fixture
def gcs_free_sim():
    """A simulator sending to a free port that the test's client (not pymavlink) will bind."""
    from sim_harness import RunningSim

    from planner.scenario import load_scenario
    from sim_gateway.simulator import SimOptions, Simulator

    port = free_udp_port()
    running = RunningSim(
        Simulator(load_scenario("paper-2uav"), SimOptions(gcs_port=port, boot_s=0.0, speedup=10.0))
    )
    yield port, running.sim
    running.close()


def test_mavsdk_health_says_armable_once_the_boot_phase_is_over():
    """MAVSDK's ``health.is_armable`` is SYS_STATUS's PREARM_CHECK health bit: False while the
    simulated autopilot initialises (arming refused), True once it could arm (it used to stay
    False for ever although arming worked); the magnetometer is reported present and healthy."""
    mavsdk = _require("mavsdk", "pip install -e .[test]")
    assert mavsdk.__version__.startswith("4.")
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
    from sim_harness import RunningSim

    from planner.scenario import load_scenario
    from sim_gateway.simulator import SimOptions, Simulator

    port = free_udp_port()
    # the boot phase lasts until the test ends it (600 s simulated at real time)
    options = SimOptions(gcs_port=port, boot_s=600.0, speedup=1.0)
    running = RunningSim(Simulator(load_scenario("paper-2uav"), options))
    sim = running.sim

    async def session() -> tuple[bool, bool, bool]:
        config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
        async with Mavsdk(config) as drone:
            await drone.add_any_connection(f"udpin://127.0.0.1:{port}")
            system = await drone.first_autopilot(timeout_s=10.0)
            assert system is not None
            telemetry = TelemetryAsync(system)
            booting = None
            async for health in telemetry.subscribe_health():
                if sim.vehicles[0].booting:
                    booting = health
                    break
            try:  # the verdict is the autopilot's: it refuses to arm while not armable
                await ActionAsync(system).arm()
                refused = False
            except Exception:  # noqa: BLE001 (MAVSDK's ActionError)
                refused = True
            sim.boot_s = 0.0  # initialisation over
            async for health in telemetry.subscribe_health():
                if health.is_armable:
                    break
            await ActionAsync(system).arm()
            return booting.is_armable, refused, health.is_magnetometer_calibration_ok

    try:
        armable_booting, refused_booting, mag_ok = asyncio.run(asyncio.wait_for(session(), 60))
    finally:
        running.close()
    assert armable_booting is False and refused_booting
    assert mag_ok
    assert sim.vehicles[0].armed
