"""The daemon against a fake swarm: the whole protocol, failures named in one line, lost links."""

from __future__ import annotations

import socket

import pytest
from loopback import run_swarmplan

from mavlink_bridge.mission.daemon import DaemonOptions, MissionDaemon
from mavlink_bridge.vehicles.discovery import DiscoveryError
from mavlink_bridge.vehicles.guided_commands import CommandRefusedError
from mavlink_bridge.vehicles.readiness import NotReadyError
from mavlink_wire.links import EndpointError
from mavlink_wire.protocol import mavlink
from planner.errors import UserError


def options(port: int, **kw: object) -> DaemonOptions:
    base = dict(
        connect=[f"udpin:127.0.0.1:{port}"],
        steps=12,
        discovery_timeout_s=5,
        ready_timeout_s=10,
        takeoff_timeout_s=10,
    )
    base.update(kw)
    return DaemonOptions(**base)  # type: ignore[arg-type]


def test_flies_fake_swarm_and_logs_a_readable_tlog(paper10, udp_port, fake_swarm_factory, tmp_path):
    swarm = fake_swarm_factory(4, udp_port)
    tlog = tmp_path / "m.tlog"
    report = MissionDaemon(paper10, options(udp_port, expect=4, tlog_path=tlog)).fly()
    result = report.result
    assert result["steps"] >= 10
    assert result["source"] == "mavlink"
    assert len(result["uavs"]) == 4
    for v in swarm.vehicles:
        assert len(v.fence_items) == len(paper10.threats)
        assert all(i.command == mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION for i in v.fence_items)
        assert v.mode == 11  # RTL at the end
        assert mavlink.MAV_CMD_DO_REPOSITION in v.commands
    from pymavlink import mavutil

    log = mavutil.mavlink_connection(str(tlog))
    kinds: dict[str, int] = {}
    while (msg := log.recv_match()) is not None:
        kinds[msg.get_type()] = kinds.get(msg.get_type(), 0) + 1
    for kind in (
        "HEARTBEAT",
        "COMMAND_INT",
        "COMMAND_ACK",
        "MISSION_ITEM_INT",
        "CAMERA_IMAGE_CAPTURED",
    ):
        assert kinds.get(kind, 0) > 0, kind


def test_missing_vehicles_named_with_endpoint(paper10, udp_port, fake_swarm_factory):
    swarm = fake_swarm_factory(2, udp_port)
    with pytest.raises(DiscoveryError) as err:
        MissionDaemon(paper10, options(udp_port, expect=4, discovery_timeout_s=1.5)).fly()
    text = str(err.value)
    assert "system id 3, 4" in text and f"udpin:127.0.0.1:{udp_port}" in text
    assert "\n" not in text
    # the two grounded, disarmed vehicles heard are not commanded into RTL on the way out
    assert all(mavlink.MAV_CMD_DO_SET_MODE not in v.commands for v in swarm.vehicles)


def test_port_in_use_is_one_clear_line(paper10, udp_port):
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    holder.bind(("127.0.0.1", udp_port))
    try:
        with pytest.raises(EndpointError, match=f"UDP port {udp_port} is already in use"):
            MissionDaemon(paper10, options(udp_port, expect=1)).fly()
    finally:
        holder.close()


def test_unreachable_tcp_endpoint(paper10, udp_port):
    with pytest.raises(EndpointError, match="nothing listens on tcp:127.0.0.1"):
        MissionDaemon(
            paper10, options(udp_port, connect=[f"tcp:127.0.0.1:{udp_port}"], expect=1)
        ).fly()


def test_arm_refusal_names_prearm_reason(paper10, udp_port, fake_swarm_factory):
    fake_swarm_factory(2, udp_port, refuse_arm="PreArm: Throttle not at zero")
    # arming is retried within the readiness window, then each vehicle is named with its reason
    with pytest.raises(
        NotReadyError,
        match="not ready to arm within .*vehicle 1 .*MAV_RESULT_FAILED.*PreArm: Throttle not at "
        "zero.*vehicle 2 ",
    ):
        MissionDaemon(paper10, options(udp_port, expect=2, ready_timeout_s=4.0)).fly()


def test_gcs_failsafe_is_set_and_confirmed_before_arming(paper10, udp_port, fake_swarm_factory):
    """Issue 12, finding 2: every vehicle flies on to its last guided target without a ground
    station (FS_GCS_ENABL 1, FS_LONG_ACTN 0), set at launch and confirmed by its PARAM_VALUE."""
    swarm = fake_swarm_factory(2, udp_port)
    MissionDaemon(paper10, options(udp_port, expect=2, steps=2)).fly()
    for v in swarm.vehicles:
        assert v.params["FS_GCS_ENABL"] == 1 and v.params["FS_LONG_ACTN"] == 0
        assert v.params["FS_SHORT_ACTN"] == 0 and v.params["FS_LONG_TIMEOUT"] == 5


def test_a_vehicle_answering_its_parameters_late_is_flown_on_its_own_airframe(
    paper10, udp_port, fake_swarm_factory
):
    """Three PX4 SITL instances at 5x on a loaded machine: one answered no parameter in the 4 s
    the airframe read waited, and was flown on the defaults (a loiter radius of 0 m). A vehicle
    that has answered none is asked on (``SILENT_READ_WINDOW_S``)."""
    fake_swarm_factory(2, udp_port, params_after_s=7.0)
    said: list[str] = []
    MissionDaemon(paper10, options(udp_port, expect=2, steps=1, progress=said.append)).fly()
    frames = [line for line in said if line.startswith("airframe vehicle")]
    assert len(frames) == 2, said
    for line in frames:
        assert "loiter radius 60 m" in line and "not reported" not in line, line


def test_a_vehicle_keeping_its_failsafe_stops_the_launch_unarmed(
    paper10, udp_port, fake_swarm_factory
):
    swarm = fake_swarm_factory(2, udp_port, keep_param="FS_GCS_ENABL")
    with pytest.raises(UserError) as err:
        MissionDaemon(paper10, options(udp_port, expect=2)).fly()
    text = str(err.value)
    assert "kept FS_GCS_ENABL = 0 when set to 1" in text and "\n" not in text
    assert "set them by hand" in text
    assert not any(v.armed for v in swarm.vehicles)


def test_command_refusal_names_result(paper10, udp_port, fake_swarm_factory):
    fake_swarm_factory(2, udp_port, refuse_command=mavlink.MAV_CMD_DO_REPOSITION)
    with pytest.raises(
        CommandRefusedError, match="refused MAV_CMD_DO_REPOSITION: MAV_RESULT_DENIED"
    ):
        MissionDaemon(paper10, options(udp_port, expect=2)).fly()


def test_cli_reports_missing_vehicles_in_one_line(udp_port, tmp_path):
    proc = run_swarmplan(
        ["daemon", "--connect", f"udpin:127.0.0.1:{udp_port}", "--scenario", "paper-10uav",
         "--expect", "3", "--timeout", "1", "--out", str(tmp_path)],
        timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2
    last = proc.stderr.strip().splitlines()[-1]
    assert "system id 1, 2, 3 did not appear within 1 s" in last
    assert f"udpin:127.0.0.1:{udp_port}" in last


def test_silent_vehicle_is_lost_then_rejoins(paper10, udp_port, fake_swarm_factory):
    swarm = fake_swarm_factory(3, udp_port)
    steps_seen: list[int] = []

    def on_step(status) -> None:  # cut vehicle 2 at step 5, bring it back at step 14
        steps_seen.append(status.step)
        if status.step == 5:
            swarm.vehicles[1].silent.set()
        if status.step == 14:
            swarm.vehicles[1].silent.clear()

    opts = options(
        udp_port, expect=3, steps=20, lost_after_s=0.6, on_step=on_step, rtl_watch_s=0.0
    )
    report = MissionDaemon(paper10, opts).fly()
    events = [(e.uav, e.event) for e in report.events]
    assert (1, "lost") in events and (1, "rejoined") in events
    assert report.result["lost_uavs"] == [1]
    assert report.result["steps"] >= 18  # the others carried on


def test_a_fence_upload_a_vehicle_ended_unheard_starts_over(udp_port, fake_swarm_factory):
    """A duplicating, delaying link (the reliability bench at 30 % loss): a late MISSION_COUNT
    restarts the vehicle's transfer after it asked for item 1, a delayed item 1 completes it
    with the next item 0, and its MISSION_ACK is lost; the vehicle, its transfer over, ignores
    items. Resending item 0 never got an answer and the upload stalled; after ``ITEM_RESENDS``
    unanswered resends it now starts over, and the fence gets through."""
    from mavlink_bridge.vehicles.fence_upload import FenceCircle, upload_fence
    from mavlink_bridge.vehicles.swarm_link import SwarmLink

    swarm = fake_swarm_factory(1, udp_port, fence_race=True)
    link = SwarmLink.open([f"udpin:127.0.0.1:{udp_port}"])
    try:
        assert link.pump_until(lambda: link.vehicle(1) is not None, 5.0)
        circles = [FenceCircle(-35.30, 149.20, 2000.0), FenceCircle(-35.33, 149.25, 3000.0)]
        upload_fence(link, [link.vehicle(1)], circles, stall_timeout_s=4.0)
    finally:
        link.close()
    vehicle = swarm.vehicles[0]
    assert vehicle.race_stage == 3  # the race was played, then a second upload went through
    assert [item.seq for item in vehicle.fence_items] == [0, 1]
