"""The harness itself against the real binary: two instances get their own instance numbers,
system ids and homes, serve MAVLink on SERIAL0 and SERIAL1, boot until the pre-arm checks pass,
and are gone (ports free again) after stop."""

from __future__ import annotations

import os
import time

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402
from sitl_harness import _tcp_port_free, homes_near  # noqa: E402

PREARM = mavutil.mavlink.MAV_SYS_STATUS_PREARM_CHECK


def _until(conn, pred, timeout_s: float):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        m = conn.recv_match(blocking=True, timeout=0.2)
        if m is not None and pred(m):
            return m
    return None


def test_two_instances_boot_and_stop_cleanly(sitl_swarm):
    homes = homes_near(-35.36, 149.17, 2, spacing_m=500.0)
    swarm = sitl_swarm(homes, speedup=10, params={"FENCE_ENABLE": 0})
    assert len({v.instance for v in swarm.vehicles}) == 2
    conns = []
    try:
        for v in swarm.vehicles:
            conns.append(
                mavutil.mavlink_connection(
                    v.master, source_system=255, source_component=190, autoreconnect=False
                )
            )
        for v, conn in zip(swarm.vehicles, conns, strict=True):
            hb = _until(conn, lambda m: m.get_type() == "HEARTBEAT", 10)
            assert hb is not None and hb.get_srcSystem() == v.system_id
            ready = _until(
                conn,
                lambda m: (
                    m.get_type() == "SYS_STATUS" and m.onboard_control_sensors_health & PREARM
                ),
                30,
            )
            assert ready is not None, f"vehicle {v.system_id} never passed its pre-arm checks"
            home = _until(conn, lambda m: m.get_type() == "HOME_POSITION", 10)
            assert home is not None
            assert abs(home.latitude / 1e7 - v.home.lat_deg) < 1e-4
            assert abs(home.longitude / 1e7 - v.home.lon_deg) < 1e-4
            side = mavutil.mavlink_connection(
                v.payload, source_system=v.system_id, source_component=100, autoreconnect=False
            )
            try:
                hb = _until(side, lambda m: m.get_type() == "HEARTBEAT", 10)
                assert hb is not None and hb.get_srcSystem() == v.system_id
            finally:
                side.close()
    finally:
        for conn in conns:
            conn.close()
    procs = [v.process for v in swarm.vehicles]
    ports = [v.port + k for v in swarm.vehicles for k in range(4)]
    swarm.stop()
    assert all(p.poll() is not None for p in procs)
    deadline = time.monotonic() + 5
    while not all(_tcp_port_free(p) for p in ports) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert all(_tcp_port_free(p) for p in ports)
