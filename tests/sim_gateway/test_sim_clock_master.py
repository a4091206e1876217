"""Only the ground station the vehicles send to drives a lockstep simulator's clock (issue 31,
finding 2): a simulator on loopback UDP, its ground station (the harness's, on the port the
vehicles send to) and a stranger on its own socket sending grants, releases and heartbeats
straight to the vehicles' ports."""

from __future__ import annotations

import socket
import time

from pymavlink.dialects.v20 import ardupilotmega as ml

RELEASE = 0xFFFFFFFF


def pack(msg: ml.MAVLink_message, sysid: int, compid: int, seq: int = 0) -> bytes:
    mav = ml.MAVLink(None, sysid, compid)
    mav.seq = seq % 256
    return bytes(msg.pack(mav))


def grant(boot_ms: int, sysid: int, compid: int = 190, seq: int = 0) -> bytes:
    return pack(ml.MAVLink_system_time_message(0, boot_ms), sysid, compid, seq)


def to_every_vehicle(sock: socket.socket, sim, frame: bytes) -> None:
    for vehicle_socket in sim.sockets:
        sock.sendto(frame, ("127.0.0.1", vehicle_socket.local_port))


def held_at(gcs, boot_ms: int) -> bool:
    return gcs.wait("GLOBAL_POSITION_INT", 1, 5, cond=lambda m: m.time_boot_ms == boot_ms)


def test_grants_from_anyone_but_the_ground_station_are_dropped_counted_and_said_once(
    gcs, sim_factory, capsys
):
    sim = sim_factory(lockstep=True, speedup=1.0, airborne=True).sim
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.bind(("127.0.0.1", 0))
    try:
        # the stranger talks first, before the ground station has granted anything: a release
        # as system 77, an hour in the ground station's own system id, a release as vehicle 1
        for k, frame in enumerate((grant(RELEASE, 77), grant(3_600_000, 255), grant(RELEASE, 1))):
            to_every_vehicle(stranger, sim, frame)
            to_every_vehicle(stranger, sim, grant(RELEASE, 77, seq=k + 1))  # each its own frame
        time.sleep(0.5)
        assert sim.sim_time_s == 0.0 and not sim.lockstep.released
        # the ground station (on the port the vehicles send to) grants 10 s: the clock moves
        gcs.heartbeat()
        gcs.mav.system_time_send(0, 10_000)
        assert held_at(gcs, 10_000)
        # from the ground station's own address, but another system id: refused
        vehicle = ("127.0.0.1", sim.sockets[0].local_port)
        gcs.conn.port.sendto(grant(RELEASE, 77, seq=9), vehicle)
        # a copy of the ground station's next grant, the very same bytes, sent ahead by the
        # stranger: refused, and it does not mask the original as a duplicate
        stranger.sendto(grant(20_000, 255, 190, seq=gcs.mav.seq), vehicle)
        time.sleep(0.3)
        assert sim.sim_time_s == 10.0 and not sim.lockstep.released
        gcs.mav.system_time_send(0, 20_000)
        assert held_at(gcs, 20_000)
        assert sim.sim_time_s == 20.0 and not sim.lockstep.released
    finally:
        stranger.close()
    # 6 frames of the stranger (each to both vehicle sockets: handled once), 1 from the ground
    # station's address as system 77, the copy
    assert sim.summary()["foreign_grants"] == 8
    assert sim.summary()["lockstep_grants"] == 2
    said = [line for line in capsys.readouterr().out.splitlines() if "refused a lockstep" in line]
    # once per sender: 77, 255 and 1 at the stranger's address, 77 at the ground station's
    assert len(said) == 4, said
    assert any("system 1 is a simulated vehicle" in line for line in said), said
    assert any("bound to system 255" in line for line in said), said


def test_a_strangers_heartbeats_do_not_hold_the_lock_once_the_ground_station_is_silent(
    gcs, sim_factory
):
    """The lock is released after --lockstep-timeout of silence of the ground station that
    drives it (its vehicles' failsafes can then act); a stranger's heartbeats, even in the
    ground station's system id, used to keep it held, the vehicles frozen."""
    sim = sim_factory(lockstep=True, speedup=1.0, airborne=True, lockstep_timeout_s=1.0).sim
    gcs.heartbeat()
    gcs.mav.system_time_send(0, 10_000)
    assert held_at(gcs, 10_000)
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger.bind(("127.0.0.1", 0))
    beat = ml.MAVLink_heartbeat_message(ml.MAV_TYPE_GCS, ml.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
    try:
        deadline = time.monotonic() + 4.0  # 4 x the timeout
        k = 0
        while not sim.lockstep.released and time.monotonic() < deadline:
            to_every_vehicle(stranger, sim, pack(beat, (77, 255)[k % 2], 190, k // 2))
            k += 1
            time.sleep(0.05)
    finally:
        stranger.close()
    assert k > 10
    assert sim.lockstep.released
    assert sim.sim_time_s >= 10.0
