"""A daemon that does not stay to watch the flight home (``--rtl-watch 0``) holds no plane for
another's way home: nobody would release it. Every plane gets RTL, and the simulator's planes
all fly it after the daemon is gone. Real processes (``swarmplan sim`` and ``swarmplan daemon``
in lockstep) over loopback UDP."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from loopback import free_udp_port, run_swarmplan, start_swarmplan, stop
from pymavlink import mavutil
from test_track_safety import SWAPPED_SIDES

from mavlink_wire.protocol import PLANE_MODE_RTL

#: the corridor after 6 steps: the planes end 2.6 km apart flying at each other, and a daemon
#: that watches the flight home holds one while the other leaves first (test_track_safety.py)
FACING = SWAPPED_SIDES.replace("steps = 16", "steps = 6")


def modes_heard(port: int, seconds: float) -> dict[int, int]:
    """The last flight mode (custom_mode) each system id reports to ``port`` within ``seconds``."""
    link = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255)
    modes: dict[int, int] = {}
    try:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            msg = link.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
            if msg is not None and msg.get_srcComponent() == 1:
                modes[msg.get_srcSystem()] = msg.custom_mode
    finally:
        link.close()
    return modes


@pytest.mark.timeout(150)
def test_a_daemon_that_does_not_watch_the_flight_home_sends_every_plane_home(tmp_path: Path):
    scenario = tmp_path / "facing.toml"
    scenario.write_text(FACING)
    port = free_udp_port()
    sim = start_swarmplan(
        ["sim", "--scenario", str(scenario), "--lockstep", "--quiet", "--gcs-port", str(port)],
        tmp_path / "sim.log",
    )
    try:
        done = run_swarmplan(
            ["daemon", "--connect", f"udpin:127.0.0.1:{port}", "--scenario", str(scenario),
             "--lockstep", "--rtl-watch", "0", "--timeout", "30", "--no-view", "--json",
             "--out", str(tmp_path / "out")],
            timeout=120,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr[-2000:]
        # the daemon is gone and the simulator runs free: what do its planes fly?
        modes = modes_heard(port, 4.0)
    finally:
        stop(sim)
    result = json.loads(done.stdout)
    assert result["steps"] == 6
    assert modes == {1: PLANE_MODE_RTL, 2: PLANE_MODE_RTL}, modes
    assert result["held_for_separation_home"] == []
    assert result["rtl_sent_to"] == [1, 2]
