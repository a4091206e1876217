"""Fault injection: the daemon and the simulator over a link that loses, delays, duplicates and
reorders datagrams (tests/reliability/udp_fault_relay.py), and the protocol pieces that make
them cope: acknowledged retries, stale-telemetry detection by timestamps, and engagements that
happen once however often (and in whatever order) their requests arrive."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import re  # noqa: E402
from collections import deque  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from loopback import start_swarmplan, stop  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as ml  # noqa: E402
from reliability_harness import last_json  # noqa: E402
from udp_fault_relay import FaultProfile, FaultRelay, MessageWithhold  # noqa: E402

from mavlink_bridge.mission.daemon import DaemonOptions, MissionDaemon  # noqa: E402
from mavlink_bridge.vehicles.autopilot_adapter import MISSION_FAILSAFE  # noqa: E402
from mavlink_bridge.vehicles.discovery import wait_for_vehicles  # noqa: E402
from mavlink_bridge.vehicles.fence_upload import FenceCircle, upload_fence  # noqa: E402
from mavlink_bridge.vehicles.gcs_failsafe import set_gcs_failsafe  # noqa: E402
from mavlink_bridge.vehicles.guided_commands import engagement_command  # noqa: E402
from mavlink_bridge.vehicles.swarm_link import SwarmLink  # noqa: E402
from mavlink_bridge.vehicles.telemetry_plausibility import PlausibilityFilter  # noqa: E402
from mavlink_bridge.vehicles.vehicle_key import VehicleKey  # noqa: E402
from mavlink_bridge.vehicles.vehicle_state import CommandAck, VehicleState  # noqa: E402
from planner.geodesy import local_km_to_geodetic  # noqa: E402
from planner.scenario import load_scenario, parse_scenario  # noqa: E402
from sim_gateway.simulator import SimOptions, Simulator  # noqa: E402

STEPS = 15


def _frame(msg, seq: int, sysid: int = 255, compid: int = 190) -> bytes:
    mav = ml.MAVLink(None, sysid, compid)
    mav.seq = seq % 256
    return bytes(msg.pack(mav))


# ---------------------------------------------------------------------- the mission over a bad link


# bounded, not timed: the watch of the final RTL flies ~500 simulated s more, which a loaded
# 2-core machine takes well over the 150 s this test had (45 s on an idle one)
@pytest.mark.timeout(300)
def test_ten_uav_mission_at_20_percent_loss_and_100ms_jitter_has_no_violations(tmp_path: Path):
    scenario = load_scenario("paper-10uav")
    daemon = MissionDaemon(
        scenario,
        DaemonOptions(
            connect=["udpin:127.0.0.1:0"],
            seed=4,
            steps=STEPS,
            lockstep=True,  # simulated time waits for the daemon: as fast as the link allows
            lost_after_s=3.0,
            discovery_timeout_s=30,
            command_retry_s=0.2,  # a little above this link's worst round trip (2 x 100 ms)
            time_scale=100,
            tlog_path=tmp_path / "m.tlog",
        ),
    )
    link = daemon.connect()
    profile = FaultProfile(loss=0.2, jitter_s=0.1, duplicate=0.05, reorder=0.05)
    relay = FaultRelay(link.endpoints[0].port, scenario.uav_count, profile, seed=4)
    relay.start()
    log = tmp_path / "sim.log"
    sim = start_swarmplan(
        ["sim", "--scenario", "paper-10uav", "--seed", "4", "--lockstep", "--speedup", "100",
         "--per-vehicle-ports", str(relay.base_port), "--quiet"],
        log,
    )  # fmt: skip
    try:
        result = daemon.fly().result
    finally:
        stop(sim)
        relay.stop()
    summary = last_json(log)
    c = relay.counters
    # the link really was that bad, both ways
    assert 0.16 < c.dropped / c.received < 0.24
    assert c.duplicated > 50 and c.reordered > 50 and c.by_direction["down"] > 500
    # and the mission completed, every UAV every step, with no safety violation
    assert result["steps"] == STEPS
    assert all(len(u["track_km"]) == STEPS + 1 for u in result["uavs"])
    assert result["violations"] == {"threat": 0, "separation": 0, "turn": 0, "range": 0}
    assert result["lost_uavs"] == []
    assert summary is not None and summary["fence_breaches"] == 0
    # the simulator saw the duplicates and dropped them; no engagement was lost or doubled
    assert summary["duplicates"] > 0
    assert result["engaged_count"] == len(scenario.targets) - summary["targets_left"]


ONE_PLANE = """
name = "one-plane"
steps = 2
[uavs]
count = 1
[[uavs.start]]
x_km = 50.5
y_km = 50.5
[[targets]]
kind = "unknown_position"
x_km = 20
y_km = 20
value = 1
"""


class FirstArmedHeartbeatLost(MessageWithhold):
    """``FaultRelay`` withhold: the first HEARTBEAT a vehicle sends armed is lost on its way."""

    def __init__(self) -> None:
        super().__init__()
        self.dropped = 0

    def judge(self, message: ml.MAVLink_message, direction: str) -> bool:
        armed = (
            message.get_type() == "HEARTBEAT" and message.base_mode & ml.MAV_MODE_FLAG_SAFETY_ARMED
        )
        if direction == "up" and not self.dropped and armed and message.get_srcComponent() == 1:
            self.dropped += 1
            return True
        return False


def _arm_clock_s(tmp_path: Path, lose_heartbeat: bool) -> float:
    """One lockstep mission of ONE_PLANE through the relay: the vehicle's clock when the daemon
    saw it armed (its line 'armed 1 vehicles after ... (vehicle clocks A..B s since boot)')."""
    said: list[str] = []
    daemon = MissionDaemon(
        parse_scenario(ONE_PLANE),
        DaemonOptions(
            connect=["udpin:127.0.0.1:0"], seed=1, lockstep=True, discovery_timeout_s=30,
            rtl_watch_s=0.0, progress=said.append,
        ),
    )  # fmt: skip
    link = daemon.connect()
    withhold = FirstArmedHeartbeatLost() if lose_heartbeat else None
    relay = FaultRelay(link.endpoints[0].port, 1, FaultProfile(), seed=1, withhold=withhold)
    relay.start()
    scenario = tmp_path / f"one-{lose_heartbeat}.toml"
    scenario.write_text(ONE_PLANE)
    sim = start_swarmplan(
        ["sim", "--scenario", str(scenario), "--lockstep", "--speedup", "100",
         "--per-vehicle-ports", str(relay.base_port), "--quiet"],
        tmp_path / f"sim-{lose_heartbeat}.log",
    )  # fmt: skip
    try:
        daemon.fly()
    finally:
        stop(sim)
        relay.stop()
    assert withhold is None or withhold.dropped == 1
    line = next(text for text in said if text.startswith("armed "))
    return float(re.search(r"vehicle clocks ([\d.]+)\.\.", line).group(1))


@pytest.mark.timeout(120)
def test_a_lost_heartbeat_does_not_change_when_a_lockstep_mission_starts(tmp_path: Path):
    """In lockstep a seed flies one mission: the daemon grants the simulator time only when the
    vehicles need it. An accepted arm waited one heartbeat period (1 s of wall time) for the
    heartbeat that shows it, then granted a decision period: a heartbeat lost, or one late on a
    loaded machine (seen: 1.7 s, paper-10uav seed 4 under CI), armed the planes 10 simulated s
    later, and every target had moved on (coverage 89.4 -> 83.1 %)."""
    assert _arm_clock_s(tmp_path, lose_heartbeat=True) == _arm_clock_s(tmp_path, False)


@contextmanager
def ten_vehicles_through(profile: FaultProfile, seed: int):
    """paper-10uav's simulator behind the fault relay, its vehicles found on a SwarmLink:
    yields (link, vehicles, relay); everything is stopped and closed after."""
    ids = list(range(1, load_scenario("paper-10uav").uav_count + 1))
    link = SwarmLink.open(["udpin:127.0.0.1:0"], accept_vehicle=lambda key: key.system_id in ids)
    relay = FaultRelay(link.endpoints[0].port, len(ids), profile, seed=seed)
    relay.start()
    sim = start_swarmplan(
        ["sim", "--scenario", "paper-10uav", "--boot-s", "0", "--speedup", "1",
         "--per-vehicle-ports", str(relay.base_port), "--quiet"],
        Path(os.devnull),
    )  # fmt: skip
    try:
        wait_for_vehicles(link, [VehicleKey(0, i) for i in ids], 60)
        yield link, [link.vehicle(i) for i in ids], relay
    finally:
        stop(sim)
        relay.stop()
        link.close()


@pytest.mark.timeout(200)
def test_the_fence_gets_through_a_link_losing_30_percent_each_way():
    """Finding 10: at 30 % loss the fence upload restarted the whole exchange at every stall
    and gave up after 20 s in 2 of 3 runs. Three uploads in a row to ten vehicles must all
    complete, each vehicle storing every circle."""
    scenario = load_scenario("paper-10uav")
    lat, lon = local_km_to_geodetic(
        [t.x_km for t in scenario.threats], [t.y_km for t in scenario.threats], scenario.origin
    )
    circles = [
        FenceCircle(float(la), float(lo), t.radius_km * 1e3)
        for la, lo, t in zip(lat, lon, scenario.threats, strict=True)
    ]
    with ten_vehicles_through(FaultProfile(loss=0.3, jitter_s=0.05), seed=10) as (
        link, vehicles, relay,
    ):  # fmt: skip
        # each upload returns only once every vehicle answered MISSION_ACK ACCEPTED for the
        # fence (any other answer, or a stall, raises MissionUploadError naming the vehicle).
        # The vehicles' last MISSION_ACK is not asserted: an exchange restarted because its
        # ACK came late (not lost) is abandoned by the vehicle with OPERATION_CANCELLED after
        # the upload ended, which keeps the fence it stored (sim_gateway/mission_protocol.py)
        for _ in range(3):
            upload_fence(link, vehicles, circles)
    assert 0.25 < relay.counters.dropped / relay.counters.received < 0.35


@pytest.mark.timeout(150)
def test_the_gcs_failsafe_gets_through_a_link_losing_half_of_everything():
    """Issue 12: a launch at 30 % loss failed now and then with "did not confirm FS_LONG_TIMEOUT
    after 12 tries" (a PARAM_SET and its PARAM_VALUE both get through in half the tries). Over a
    link losing 50 % each way, three launches in a row set and confirm every parameter of the
    GCS failsafe on ten vehicles (with 12 tries each of a launch's 40 parameters went
    unconfirmed about 3 % of the time)."""
    with ten_vehicles_through(FaultProfile(loss=0.5), seed=12) as (link, vehicles, relay):
        for _ in range(3):  # each returns only once every vehicle confirmed every value
            set_gcs_failsafe(link, vehicles)
    for v in vehicles:
        for name, value, _ in MISSION_FAILSAFE.parameters():
            assert v.params[name] == value, (v.system_id, name)
    assert 0.45 < relay.counters.dropped / relay.counters.received < 0.55


# ---------------------------------------------------------------------- engagements happen once


@pytest.fixture
def sim() -> Simulator:
    options = SimOptions(gcs_port=9, airborne=True, boot_s=0.0)  # sends go nowhere
    simulator = Simulator(load_scenario("paper-2uav"), options)
    yield simulator
    simulator.close()


def test_duplicated_and_reordered_engagement_requests_engage_once(sim: Simulator):
    engaged = []
    sim.engage = lambda index: engaged.append(index) or type(sim).engage(sim, index)
    requests = {
        seq: ml.MAVLink_command_long_message(
            1, 100, ml.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 0, 1, seq, 0, 0, 0
        )
        for seq in (1, 2, 3)
    }
    # sequence numbers 1, 2, 3 sent (MAVLink seq 10, 11, 12); the link duplicates every one,
    # delivers 3 before 2, and a retry of 1 (new MAVLink seq) comes last
    order = [(1, 10), (1, 10), (3, 12), (2, 11), (3, 12), (2, 11), (1, 13)]
    for engagement, seq in order:
        sim.handle_datagram(_frame(requests[engagement], seq))
    assert engaged == [0, 0]  # engagement 1 and 3 once each; 2 arrived overtaken (stale)
    assert sim.stats.duplicates == 3
    assert sim.stats.stale_commands == 1
    assert sorted(sim.vehicles[0].engagements._by_sequence) == [1, 3]


def test_a_reposition_overtaken_on_the_way_is_not_applied(sim: Simulator):
    vehicle = sim.vehicles[0]
    lat0, lon0 = sim.origin.lat_deg, sim.origin.lon_deg

    def reposition(north_deg: float):
        return ml.MAVLink_command_int_message(
            1, 1, ml.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, ml.MAV_CMD_DO_REPOSITION, 0, 0,
            -1, 1, 0, 0, round((lat0 + north_deg) * 1e7), round((lon0 + 0.3) * 1e7), 500,
        )  # fmt: skip

    sim.handle_datagram(_frame(reposition(0.5), 21))  # the newer target arrives first
    newer = (vehicle.guided.x_m, vehicle.guided.y_m)
    sim.handle_datagram(_frame(reposition(0.1), 20))  # the older one, delayed on the way
    assert (vehicle.guided.x_m, vehicle.guided.y_m) == newer
    assert sim.stats.stale_commands == 1
    # a sender that restarted its counter far behind (a restarted daemon) is obeyed
    sim.handle_datagram(_frame(reposition(0.2), 200))
    assert (vehicle.guided.x_m, vehicle.guided.y_m) != newer


# ---------------------------------------------------------------------- the daemon's side


class _Link:
    mav = None


def _position(time_boot_ms: int, lat: float) -> ml.MAVLink_message:
    msg = ml.MAVLink_global_position_int_message(
        time_boot_ms, round(lat * 1e7), 1490000000, 600000, 500000, 10000, 0, 0, 9000
    )
    msg._header = ml.MAVLink_header(msg.id, srcSystem=1, srcComponent=1)
    return msg


def test_stale_positions_are_dropped_and_a_reboot_is_followed():
    trust = PlausibilityFilter()
    v = VehicleState(1, _Link())

    def hear(time_boot_ms: int, lat: float, wall_s: float) -> None:
        msg = _position(time_boot_ms, lat)
        if trust.admit(1, msg, wall_s):
            v.handle(msg, wall_s)

    hear(5000, -35.0, 0.0)
    hear(4000, -35.0005, 0.1)  # delayed: older than what we have
    assert (v.time_boot_ms, v.lat_deg) == (5000, pytest.approx(-35.0))
    assert trust.counts.stale_positions == 1
    hear(6000, -35.001, 0.2)
    assert v.lat_deg == pytest.approx(-35.001)
    # the clock restarted (a reboot): followed only once the old clock is silent and the new
    # one has run on for a while, never on a few frames interleaved with the live clock
    hear(100, -35.001, 0.3)
    hear(7000, -35.002, 0.4)  # the old clock is alive: the candidate is dropped
    for k, t in enumerate((200, 300, 400, 500, 600)):
        hear(t, -35.002, 0.5 + 0.3 * k)
    assert (v.time_boot_ms, trust.counts.clock_rebases) == (600, 1)
    assert trust.notices[-1].startswith("vehicle 1: clock restarted (time 7.0 s -> 0.2 s")
    hear(700, -35.002, 2.0)
    assert v.time_boot_ms == 700
    # an autopilot whose position estimate settles after boot (ArduPlane SITL): its reports
    # jump 4.4 km ahead at once; followed the same way, and said as what it is
    for k, t in enumerate((10_000, 10_200, 10_400, 10_600, 10_800)):
        hear(t, -34.962, 2.1 + 0.3 * k)
    assert (v.lat_deg, trust.counts.clock_rebases) == (pytest.approx(-34.962), 2)
    assert trust.notices[-1].startswith("vehicle 1: position jumped 4.4 km (time 0.7 s -> 10.0 s")


def test_the_placeholder_before_the_first_position_is_not_a_place():
    """ArduPlane SITL's first ~8 s of GLOBAL_POSITION_INT lie within a few metres of latitude 0,
    longitude 0 (its position estimate has no origin yet), then at its home (these are the
    values of a SITL run's tlog). Believed, the home was a 14,952 km jump: refused as too fast
    and then followed with a warning of a "clock restarted" on every plane at every start."""
    trust = PlausibilityFilter()
    v = VehicleState(1, _Link())

    def hear(time_boot_ms: int, lat_e7: int, lon_e7: int, wall_s: float) -> bool:
        msg = ml.MAVLink_global_position_int_message(
            time_boot_ms, lat_e7, lon_e7, 600000, 70, 0, 0, 0, 65535
        )
        msg._header = ml.MAVLink_header(msg.id, srcSystem=1, srcComponent=1)
        believed = trust.admit(1, msg, wall_s)
        if believed:
            v.handle(msg, wall_s)
        return believed

    early = [(2045, 0, 0), (3064, 0, 0), (4045, 2130, -533), (9064, 3105, -815)]
    assert not any(hear(ms, lat, lon, ms / 1e3) for ms, lat, lon in early)
    assert hear(10064, -353497390, 1491927403, 10.064)
    assert v.lat_deg == pytest.approx(-35.349739)
    assert (trust.counts.no_position, trust.counts.clock_rebases, trust.notices) == (4, 0, [])
    # once it has a place, a report at 0, 0 is a jump no plane can fly
    assert not hear(11064, 0, 0, 11.064)
    assert trust.counts.too_fast == 1


def _look(index: int, url: str) -> ml.MAVLink_message:
    msg = ml.MAVLink_camera_image_captured_message(
        0, 0, 0, -353000000, 1490000000, 0, 0, [1, 0, 0, 0], index, 1, url.encode()
    )
    msg._header = ml.MAVLink_header(msg.id, srcSystem=1, srcComponent=100)
    return msg


def test_look_parts_duplicated_or_out_of_order_merge_into_one_look():
    v = VehicleState(1, _Link())
    v.handle(_look(7, "look+:3,3"))  # the continuation overtook its first part
    assert v.latest_look == -1  # not a look yet
    v.handle(_look(7, "look:0,1;-2,0"))
    v.handle(_look(7, "look:0,1;-2,0"))  # duplicated
    v.handle(_look(7, "look+:3,3"))
    assert v.latest_look == 7
    assert sorted(v.looks[7].offsets) == [(-2, 0), (0, 1), (3, 3)]
    v.handle(_look(4_000_000_000, "look:"))  # an absurd look number cannot stall later looks
    assert v.latest_look == 7


def test_a_late_engagement_ack_is_not_taken_for_the_next_request():
    v = VehicleState(1, _Link())
    cmd = engagement_command(v, 5)
    cmd._serial_before = 0
    late = CommandAck(ml.MAV_CMD_IMAGE_START_CAPTURE, 0, 9, 0.0, 1, 100, 4)  # answers seq 4
    mine = CommandAck(ml.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 0.0, 2, 100, 5)
    v.ack_log = deque([late, mine])
    assert not cmd.answered_by(late) and cmd.answered_by(mine)
