"""Loss and return (vehicle_loss.py) and the return home at exit (rtl_at_exit.py) driven on their
own: vehicles known only from the MAVLink frames they sent (parsed by VehicleState's handlers),
each bound to a real (unopened) TCP endpoint whose connection can go away. The whole daemon
around them is tested over real links in test_vehicle_loss_and_exit.py and tests/sitl."""

from __future__ import annotations

import math

from mavlink_bridge.results.mission_result import (
    MissionAccount,
    link_event_rows,
    lost_vehicle_lines,
)
from mavlink_bridge.vehicles.vehicle_loss import LossWatch
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_bridge.way_home.rtl_at_exit import HomeWatch, rtl_line, rtl_recipients
from mavlink_wire.links import VehicleLink, parse_endpoint
from mavlink_wire.protocol import PLANE_MODE_GUIDED, PLANE_MODE_RTL, mavlink

HOME = (-35.0, 149.0)
ARMED = mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
DISARMED = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


def _vehicle(sysid: int) -> VehicleState:
    endpoint = parse_endpoint(f"tcp:127.0.0.1:{5750 + 10 * sysid}")
    return VehicleState(sysid, VehicleLink(sysid, endpoint, None))


def _hear(v: VehicleState, msg: mavlink.MAVLink_message, now_s: float = 0.0) -> None:
    mav = mavlink.MAVLink(None, v.system_id, 1)
    v.handle(mavlink.MAVLink(None).parse_char(msg.pack(mav)), now_s)


def _heartbeat(v: VehicleState, base_mode: int, mode: int, now_s: float = 0.0) -> None:
    msg = mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode, mode,
        mavlink.MAV_STATE_ACTIVE, 3,
    )  # fmt: skip
    _hear(v, msg, now_s)


def _position(
    v: VehicleState, north_km: float, alt_m: float, time_ms: int, now_s: float = 0.0
) -> None:
    lat = HOME[0] + math.degrees(north_km / 6371.0)
    msg = mavlink.MAVLink_global_position_int_message(
        time_ms, int(lat * 1e7), int(HOME[1] * 1e7), 0, int(alt_m * 1e3), 0, 0, 0, 0
    )
    _hear(v, msg, now_s)


def _home(v: VehicleState) -> None:
    msg = mavlink.MAVLink_home_position_message(
        int(HOME[0] * 1e7), int(HOME[1] * 1e7), 0, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0
    )
    _hear(v, msg)


def test_each_vehicle_is_lost_for_its_own_reason_and_rejoins_when_back():
    vehicles = [_vehicle(1), _vehicle(2), _vehicle(3)]
    for v in vehicles:
        _heartbeat(v, ARMED, PLANE_MODE_GUIDED)
    said: list[str] = []
    phase = {"in_mission": False}
    account = MissionAccount()
    watch = LossWatch(
        lambda: vehicles, account, 3.0, in_mission=lambda: phase["in_mission"], say=said.append
    )

    # during the launch a disarmed vehicle is not lost (it has not armed yet)
    _heartbeat(vehicles[1], DISARMED, 0, 0.5)
    _heartbeat(vehicles[1], DISARMED, 0, 1.0)
    watch.watch(0, now=1.0)
    assert not any(v.lost for v in vehicles)

    phase["in_mission"] = True
    # a heartbeat disarmed may be one from before: only the next one loses it
    watch.watch(1, now=1.0)
    assert not vehicles[1].lost
    _heartbeat(vehicles[1], DISARMED, 0, 1.05)
    watch.watch(1, now=1.05)
    assert vehicles[1].lost and watch.reasons == {1: "disarmed"}
    _heartbeat(vehicles[2], ARMED, PLANE_MODE_RTL, 1.1)
    watch.watch(1, now=1.1)
    assert not vehicles[2].lost
    _heartbeat(vehicles[2], ARMED, PLANE_MODE_RTL, 1.2)
    watch.watch(1, now=1.2)
    assert vehicles[2].lost and watch.reasons[2] == "left GUIDED (now RTL)"
    assert not vehicles[0].lost  # the others go on

    # vehicle 1's TCP connection closes: lost with its endpoint named, the others untouched
    vehicles[0].link.endpoint.went_away("connection closed by the vehicle")
    watch.watch(2, now=1.3)
    assert vehicles[0].lost
    assert watch.reasons[0] == "link tcp:127.0.0.1:5760: connection closed by the vehicle"

    # vehicle 2 armed and back in GUIDED, heard just now: it rejoins; vehicle 3 still off
    _heartbeat(vehicles[1], ARMED, PLANE_MODE_GUIDED, 2.0)
    watch.watch(3, now=2.0)
    assert not vehicles[1].lost and vehicles[2].lost and 1 not in watch.reasons
    # vehicle 1's link up again (reconnected) and heard: it rejoins
    vehicles[0].link.endpoint.closed_reason = None
    _heartbeat(vehicles[0], ARMED, PLANE_MODE_GUIDED, 2.1)
    watch.watch(4, now=2.1)
    assert not vehicles[0].lost

    # silence: lost after lost_after_s, whatever the phase (vehicle 2 last heard at 2.0)
    watch.watch(5, now=2.1 + 3.5)
    assert vehicles[0].lost and watch.reasons[0] == "silent 3.5 s"
    assert watch.reasons[1] == "silent 3.6 s"

    events = [(e.step, e.uav, e.event, e.reason) for e in account.events]
    assert events == [
        (1, 1, "lost", "disarmed"),
        (1, 2, "lost", "left GUIDED (now RTL)"),
        (2, 0, "lost", "link tcp:127.0.0.1:5760: connection closed by the vehicle"),
        (3, 1, "rejoined", ""),
        (4, 0, "rejoined", ""),
        (5, 0, "lost", "silent"),
        (5, 1, "lost", "silent"),
    ]
    assert said[0] == "vehicle 2 lost at step 1 (disarmed); the others go on"
    assert "vehicle 2 rejoined at step 3" in said


def test_a_plane_back_from_a_reboot_disarmed_stays_lost_and_the_result_says_so():
    """An autopilot that rebooted mid-mission (its TCP link closed, then up again) comes back
    disarmed on the ground: said once as back but still lost (not launched again into a swarm in
    flight), in the events and in the summary's lines; armed and in GUIDED it rejoins."""
    plane = _vehicle(1)
    _heartbeat(plane, ARMED, PLANE_MODE_GUIDED)
    said: list[str] = []
    account = MissionAccount()
    watch = LossWatch(lambda: [plane], account, 3.0, in_mission=lambda: True, say=said.append)
    plane.link.endpoint.went_away("connection closed by the vehicle")
    watch.watch(2, now=0.5)
    plane.link.endpoint.closed_reason = None  # reconnected: the rebooted autopilot speaks
    for k in range(3):
        _heartbeat(plane, DISARMED, 0, 5.0 + k)
        watch.watch(4 + k, now=5.0 + k)
    assert plane.lost and watch.reasons[0] == "disarmed"
    events = [(e.step, e.event, e.reason) for e in account.events]
    assert events[1:] == [(4, "back", "disarmed")]
    assert said[-1] == (
        "vehicle 1 is back at step 4 but disarmed: it stays lost (a plane is not launched into "
        "the swarm in flight; it rejoins armed and in GUIDED)"
    )
    result = {
        "lost_uavs": [0],
        "link_events": link_event_rows(account.events, [1]),
        "rtl_not_sent": {"1": "on the ground, disarmed"},
    }
    assert lost_vehicle_lines(result) == [
        "lost vehicles   1 (system ids)",
        "  vehicle 1     lost at step 2 (link tcp:127.0.0.1:5760: connection closed by the "
        "vehicle); back at step 4 (disarmed); not launched again mid-mission; no RTL: on the "
        "ground, disarmed",
    ]
    # flown up and switched to GUIDED by its pilot: it rejoins
    _heartbeat(plane, ARMED, PLANE_MODE_GUIDED, 9.0)
    watch.watch(8, now=9.0)
    assert not plane.lost and account.events[-1].event == "rejoined"


def test_rtl_goes_to_airborne_reachable_vehicles_only():
    flying, grounded, armed_on_ground, closed, silent = (_vehicle(i) for i in range(1, 6))
    for v, base, alt in (
        (flying, ARMED, 120.0),
        (grounded, DISARMED, 0.0),
        (armed_on_ground, ARMED, 0.5),
        (closed, ARMED, 120.0),
        (silent, ARMED, 120.0),
    ):
        _heartbeat(v, base, PLANE_MODE_GUIDED, 10.0)
        _position(v, 1.0, alt, 5000, 10.0)
    closed.link.endpoint.went_away("connection closed by the vehicle")
    _heartbeat(silent, ARMED, PLANE_MODE_GUIDED, 2.0)  # last heard 8 s before

    to, why_not = rtl_recipients([silent, closed, armed_on_ground, grounded, flying], 3.0, 10.0)
    assert [v.system_id for v in to] == [1]
    assert {str(key): why for key, why in why_not.items()} == {
        "2": "on the ground, disarmed",
        "3": "on the ground",
        "4": "unreachable: connection closed by the vehicle",
        "5": "unreachable: silent 8 s",
    }
    line = rtl_line([flying.key], [], why_not)
    assert line.startswith("RTL sent to vehicle 1 (accepted by none); not to 2 (on the ground")
    assert rtl_line([], [], {}) == "RTL sent to no vehicle (none airborne and reachable)"


def test_a_plane_is_home_after_a_whole_circle_near_it():
    plane, disarmed = _vehicle(1), _vehicle(2)
    for v in (plane, disarmed):
        _home(v)
        _heartbeat(v, ARMED, PLANE_MODE_RTL)
        _position(v, 8.0, 100.0, 1000)
    watch = HomeWatch([plane, disarmed], near_km=0.58, speed_mps=22.0)
    circle_ms = 2e6 * math.pi * 0.08 / 22.0  # an 80 m loiter circle at 22 m/s: ~23 s
    assert math.isclose(watch.circle_ms, circle_ms)
    assert math.isclose(watch.limit_s(None), 8000 / 22.0 + circle_ms / 1e3 + 120.0, rel_tol=1e-3)
    assert watch.limit_s(30.0) == 30.0
    assert not watch.home()

    _heartbeat(disarmed, DISARMED, PLANE_MODE_RTL)  # landed and disarmed: not waited for
    _position(plane, 0.3, 100.0, 2000)  # near home
    assert not watch.home()
    _position(plane, 0.7, 100.0, 2000 + int(circle_ms / 2))  # wide of it: starts again
    assert not watch.home()
    _position(plane, 0.2, 100.0, 3000 + int(circle_ms / 2))
    assert not watch.home()  # (asked at every pump: every position is seen)
    _position(plane, 0.1, 100.0, 3000 + int(circle_ms) - 10)
    assert not watch.home()
    _position(plane, 0.2, 100.0, 3000 + int(circle_ms / 2) + int(circle_ms) + 1)
    assert watch.home()
