"""Lockstep: simulated time moves only as far as the ground station grants (SYSTEM_TIME without
UTC), the vehicles say where they hold, a release lets it run, a real clock is not a grant."""

from __future__ import annotations

import time

from loopback import run_swarmplan
from sim_harness import GroundStation, start_sim


def _times(gcs, sysid: int, seconds: float) -> list[int]:
    """time_boot_ms of every GLOBAL_POSITION_INT of one vehicle heard within ``seconds``."""
    out = []
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        m = gcs.wait("GLOBAL_POSITION_INT", sysid, timeout=left)
        if m is not None:
            out.append(m.time_boot_ms)
    return out


def test_time_holds_until_granted_then_runs_to_the_horizon(gcs, sim_factory):
    running = sim_factory(lockstep=True, speedup=1.0, airborne=True)
    sim = running.sim
    gcs.heartbeat()
    held = _times(gcs, 1, 1.0)
    assert held and set(held) == {0}  # nobody granted anything: simulated time stays at 0
    # a ground station's real clock (UTC set) is not a grant
    gcs.mav.system_time_send(1_700_000_000_000_000, 5000)
    assert set(_times(gcs, 2, 0.5)) == {0}
    # grant 10 s: the vehicles run there at once (speedup 1 would take 10 s) and hold
    gcs.mav.system_time_send(0, 10_000)
    before_marker = []  # what vehicle 1 sent up to its hold marker, in order
    marker = None
    deadline = time.monotonic() + 5
    while marker is None and time.monotonic() < deadline:
        m = gcs.wait(["GLOBAL_POSITION_INT", "CAMERA_IMAGE_CAPTURED"], 1, timeout=0.5)
        if m is not None and m.get_type() == "GLOBAL_POSITION_INT" and m.time_boot_ms >= 10_000:
            marker = m  # (telemetry on the way there, paced by the wall clock, may come first)
        elif m is not None:
            before_marker.append(m)
    assert marker is not None and marker.time_boot_ms == 10_000
    # the look of that instant (a decision boundary) came before the hold marker
    assert any(
        m.get_type() == "CAMERA_IMAGE_CAPTURED" and m.time_boot_ms == 10_000 for m in before_marker
    )
    assert set(_times(gcs, 1, 0.5)) == {10_000}
    assert sim.sim_time_s == 10.0 and sim.decision_step == 1
    # the look of that instant came before the hold marker
    look = [m for m in [gcs.wait("CAMERA_IMAGE_CAPTURED", 1, timeout=0.1)] if m]
    assert all(m.time_boot_ms <= 10_000 for m in look)
    # release: it runs on at its own pace
    gcs.mav.system_time_send(0, 0xFFFFFFFF)
    later = gcs.wait("GLOBAL_POSITION_INT", 1, timeout=5, cond=lambda m: m.time_boot_ms > 10_000)
    assert later is not None
    assert sim.summary()["lockstep_grants"] == 1  # one horizon granted; the release is not one


def test_same_commands_at_the_same_holds_fly_the_same_path():
    """Two lockstep runs, a guided target sent at the same hold: identical positions, however
    long the ground station took before and after its command."""
    tracks = []
    for pause in (0.0, 0.4):
        gcs = GroundStation()
        running = start_sim(gcs.port, lockstep=True, airborne=True, seed=3)
        try:
            gcs.ensure_peer()
            gcs.heartbeat()
            gcs.mav.system_time_send(0, 10_000)
            here = gcs.wait("GLOBAL_POSITION_INT", 1, 5, cond=lambda m: m.time_boot_ms == 10_000)
            assert here is not None
            time.sleep(pause)
            ack = gcs.command_int(
                1, 192, 6, p2=1, x=here.lat + 200_000, y=here.lon - 100_000, z=100.0
            )
            assert ack is not None and ack.result == 0
            time.sleep(pause)
            gcs.mav.system_time_send(0, 40_000)
            m = gcs.wait("GLOBAL_POSITION_INT", 1, 5, cond=lambda m: m.time_boot_ms == 40_000)
            assert m is not None
            tracks.append((m.lat, m.lon, m.hdg))
        finally:
            running.close()
            gcs.close()
    assert tracks[0] == tracks[1]


def test_fast_and_lockstep_together_is_one_line_exit_2():
    proc = run_swarmplan(["sim", "--fast", "--lockstep", "--gcs-port", "9"], timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "--fast and --lockstep" in lines[0]


def test_the_heartbeat_of_a_horizon_comes_before_any_position_stamped_with_it(gcs, sim_factory):
    """A position stamped with the granted horizon tells the daemon the vehicle holds there; the
    HEARTBEAT of that instant (its system_status) must be out before it. The once-per-simulated-
    second positions used to go first, and a daemon waiting for STANDBY at the end of the boot
    phase then granted one period more on some runs: the same seed flew different missions."""
    sim_factory(lockstep=True, speedup=1.0, boot_s=10.0)
    gcs.heartbeat()
    gcs.mav.system_time_send(0, 10_000)  # the boot phase ends exactly at the horizon
    previous = None
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        m = gcs.wait(["HEARTBEAT", "GLOBAL_POSITION_INT"], 1, timeout=0.5)
        if m is None or m.get_srcComponent() != 1:
            continue
        if m.get_type() == "GLOBAL_POSITION_INT" and m.time_boot_ms >= 10_000:
            break
        previous = m
    else:
        raise AssertionError("vehicle 1 never held at 10 s")
    assert m.time_boot_ms == 10_000
    assert previous is not None and previous.get_type() == "HEARTBEAT", previous
    assert previous.system_status == 3  # MAV_STATE_STANDBY: booted, at the very horizon


def test_no_gcs_failsafe_while_the_ground_station_holds_the_clock(gcs, sim_factory):
    """In lockstep no simulated time passes while the ground station computes: a wall-clock
    silence longer than FS_LONG_TIMEOUT is no failsafe until the lock is released."""
    from pymavlink.dialects.v20 import ardupilotmega as ml

    running = sim_factory(lockstep=True, speedup=1.0, airborne=True)
    vehicle = running.sim.vehicles[0]
    gcs.heartbeat()
    for name, value in (("FS_GCS_ENABL", 1), ("FS_LONG_TIMEOUT", 1.0), ("FS_LONG_ACTN", 0)):
        gcs.mav.param_set_send(1, 1, name.encode(), value, ml.MAV_PARAM_TYPE_REAL32)
        assert gcs.wait("PARAM_VALUE", 1, cond=lambda m, n=name: m.param_id == n) is not None
    gcs.mav.system_time_send(0, 10_000)
    assert gcs.wait("GLOBAL_POSITION_INT", 1, timeout=5, cond=lambda m: m.time_boot_ms >= 10_000)
    time.sleep(2.5)  # silence, held: 2.5 x FS_LONG_TIMEOUT of wall time
    assert vehicle.failsafe.stage == 0 and running.sim.sim_time_s == 10.0
    gcs.mav.system_time_send(0, 0xFFFFFFFF)  # released: now the silence counts
    text = gcs.wait("STATUSTEXT", 1, timeout=5, cond=lambda m: "GCS Failsafe On" in m.text)
    assert text is not None and vehicle.failsafe.stage == 2
