"""Paced time (the vehicles' clock runs on its own, as real aircraft and SITL do): a decision
step bounds how long it waits for acknowledgements, and a daemon that falls behind the
vehicles' clock says so and counts it."""

from __future__ import annotations

import time

import numpy as np
from test_daemon_protocol import options

from mavlink_bridge.mission.daemon import MissionDaemon
from mavlink_bridge.vehicles.guided_commands import request_message_command, send_commands
from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_wire.protocol import mavlink


def test_a_stalled_step_is_counted_late_and_said_once(paper10, udp_port, fake_swarm_factory):
    fake_swarm_factory(2, udp_port)  # 50x: a 10 s decision period is 0.2 s of wall time
    said: list[str] = []
    late_before_stall: list[int] = []
    # told the swarm's true speed (the plausibility filter refuses a clock running more than
    # 4x the told one); no start-up refusal: this test stalls the daemon on purpose
    daemon = MissionDaemon(
        paper10,
        options(udp_port, expect=2, progress=said.append, time_scale=50.0, check_time_scale=False),
    )

    def on_step(status) -> None:
        if status.step == 4:
            late_before_stall.append(daemon.account.late_steps)
            time.sleep(0.8)  # the planner stalls for ~40 s of the vehicles' clock

    daemon.options.on_step = on_step
    result = daemon.fly().result
    assert late_before_stall == [0]
    assert result["late_steps"] >= 1
    warnings = [s for s in said if "behind the vehicles' clock" in s]
    assert len(warnings) == 1 and "--time-scale" in warnings[0] and "step 5" in warnings[0]


def test_acknowledgements_are_awaited_until_the_deadline_only(udp_port, fake_swarm_factory):
    """A vehicle that hears nothing: without a deadline every attempt is made; with one the
    batch gives up when it passes (the step's commands go again at the next step)."""
    swarm = fake_swarm_factory(1, udp_port)
    link = SwarmLink.open([f"udpin:127.0.0.1:{udp_port}"])
    try:
        link.pump_until(lambda: link.vehicle(1) is not None, 5.0)
        vehicle = link.vehicle(1)
        swarm.vehicles[0].silent.set()
        home = mavlink.MAVLINK_MSG_ID_HOME_POSITION
        (bounded,) = send_commands(
            link, [request_message_command(vehicle, home)], 0.02, 200, time.monotonic() + 0.2
        )
        assert bounded.ack is None and 1 <= bounded.attempts < 100
        (unbounded,) = send_commands(link, [request_message_command(vehicle, home)], 0.02, 20)
        assert unbounded.ack is None and unbounded.attempts == 20
    finally:
        link.close()


def test_a_step_s_commands_are_sent_several_times_before_its_deadline(
    paper10, udp_port, fake_swarm_factory
):
    """At 20x a step's deadline is 0.3 s of wall time away, the default retry interval 0.3 s:
    a command lost once was never resent within its step, and at 30 % loss each way a third
    of the planes' targets arrived a whole step late (docs/reliability.md). Unanswered, it is
    now sent ``STEP_SENDS`` times before the deadline. With no deadline (the launch) a command
    is resent as often in the vehicles' time, over the same wall-clock window: at 20x a lost
    switch to GUIDED was resent after 6 s of flight, while the plane flew straight on."""
    from mavlink_bridge.mission.daemon import MIN_RETRY_S, STEP_SENDS

    swarm = fake_swarm_factory(1, udp_port)
    daemon = MissionDaemon(paper10, options(udp_port, expect=1, time_scale=20.0))
    link = daemon.connect()
    try:
        link.pump_until(lambda: link.vehicle(1) is not None, 5.0)
        vehicle = link.vehicle(1)
        swarm.vehicles[0].silent.set()  # hears nothing: no acknowledgement
        home = mavlink.MAVLINK_MSG_ID_HOME_POSITION
        started = time.monotonic()
        (step,) = daemon.ctx.send([request_message_command(vehicle, home)], deadline=started + 0.3)
        assert step.ack is None and step.attempts >= STEP_SENDS, step.attempts
        assert time.monotonic() - started < 0.3 + 0.2  # and no later than the deadline
        assert 0.3 / step.attempts >= MIN_RETRY_S / 2  # never faster than the floor
        started = time.monotonic()
        (launch,) = daemon.ctx.send([request_message_command(vehicle, home)], attempts=2)
        # two sends 0.3 s apart at 1x; at 20x one every 20 ms over the same 0.6 s
        assert launch.ack is None and launch.attempts == 2 * round(0.3 / MIN_RETRY_S)
        assert 0.4 < time.monotonic() - started < 1.5
    finally:
        daemon.close()


def test_measured_chord_from_the_decision_instant_is_judged(paper10):
    """In paced time a plane has flown on while its step was planned. The threat check still
    judges the chord the result will measure: from where the plane was at the decision instant
    to where it will be at the next one, not from where it is now."""
    from mavlink_bridge.safety.flight_envelope import FlightEnvelope
    from mavlink_bridge.safety.safety_envelope import SafetyEnvelope
    from mavlink_bridge.vehicles.flight_prediction import PlaneModel

    cells = SafetyEnvelope.for_scenario(paper10, 1.0, 1.0)
    envelope = FlightEnvelope(cells, PlaneModel())
    centre, radius = cells.threat_xy_km[0], float(cells.threat_radius_km[0])
    now = centre + [0.0, radius + 0.5]  # just north of the zone, flying east along it
    path = (now + np.outer(np.arange(31) * 0.1, [1.0, 0.0]))[None]  # one sample a second
    on_time = envelope._threat_clearance(path, now[None], np.zeros(1))
    assert 0.4 < on_time[0] <= 0.5
    # five seconds ago it was south of the zone: the chord to the next decision instant crosses it
    before = centre + [-1.0, -(radius + 0.5)]
    late = envelope._threat_clearance(path, before[None], np.array([5.0]))
    assert late[0] < 0


def test_without_looks_steps_keep_the_vehicles_clock_and_lateness_is_counted(
    paper10, udp_port, fake_swarm_factory
):
    """Vehicles without a camera whose clock runs at 50x while the daemon is told 25x: decision
    instants come every decision period of the vehicles' own clock (their time_boot_ms), never
    earlier, and every step that came later than 1.5 periods after the last is counted in
    late_steps. (Paced by the wall clock at the speedup it was told, the daemon decided every
    20 s of vehicle time and said 0 late steps.)"""
    fake_swarm_factory(2, udp_port, camera=False)
    instants: list[int] = []
    # (the start-up refusal of a time scale this machine cannot keep is keeping_up's test: on a
    # loaded machine it would end this one before it flies)
    daemon = MissionDaemon(
        paper10,
        options(udp_port, expect=2, steps=10, time_scale=25.0, check_time_scale=False),
    )
    daemon.options.step_listeners.append(
        lambda record: instants.append(int(record.positions_ms.max()))
    )
    result = daemon.fly().result
    assert result["steps"] == 10 and result["looks_missed"] > 0  # no camera indeed
    step_ms = 1e3 * paper10.config.step_s
    gaps = np.diff(instants[1:])  # decision step 1 on (step 0 is the start)
    assert len(gaps) == 9
    # never before its instant on the vehicles' clock (positions come every 2.5 s of it)
    schedule = instants[0] + step_ms * np.arange(len(instants))
    assert (np.array(instants) >= schedule - 2500).all(), (instants, schedule)
    assert result["late_steps"] >= int((gaps > 1.5 * step_ms).sum()), (gaps, result["late_steps"])
    assert daemon.loop.pacing is not None and daemon.loop.pacing.current.name == "vehicle clock"


def test_without_any_vehicle_clock_steps_keep_a_wall_clock_schedule_and_a_stall_is_late(udp_port):
    """Vehicles that report no time at all (no position, no SYSTEM_TIME): a decision instant
    every period of the told time scale, never before it, on a schedule whatever a step takes;
    a step whose commands go out more than half a period after its instant is counted late and
    said. (Paced this way, the daemon once said 0 late steps whatever happened.) The hold when
    late reads that same measure of the step's lateness."""
    from mavlink_bridge.mission.keeping_up import HoldWhenLate
    from mavlink_bridge.mission.pacing import PacingChoice, PacingContext
    from mavlink_bridge.results.mission_result import MissionAccount

    link = SwarmLink.open([f"udpin:127.0.0.1:{udp_port}"])
    try:
        account, said = MissionAccount(), []
        ctx = PacingContext(
            link, lambda: [], lambda step: None, step_s=10.0, time_scale=100.0,
            lost_after_s=3.0, account=account, say=said.append,
        )  # fmt: skip
        period = 0.1  # wall seconds: 10 s at 100x
        before = time.monotonic()
        pacing = PacingChoice(ctx, None)
        first = pacing.wait(1, [])
        assert pacing.current.name == "wall clock" and time.monotonic() >= before + period
        time.sleep(3 * period)  # this step stalls three periods before its commands go out
        lateness = pacing.current.lateness(first)  # measured once: counted, said, held
        assert lateness.late and lateness.seconds >= 20.0  # ~30 s of the vehicles' clock
        assert account.late_steps == 1 and "behind the vehicles' clock at step 1" in said[0]
        hold = HoldWhenLate(bound_s=10.0, say=said.append)
        assert hold.hold(1, lateness.seconds) and "holding at step 1" in said[-1]
        pacing.wait(2, [])
        # the schedule kept its phase: instants at whole periods from the start, none skipped
        # twice
        periods = (pacing.wall.due_s - pacing.wall.start_s) / period
        assert periods >= 4 and abs(periods - round(periods)) < 1e-6
        assert time.monotonic() >= pacing.wall.due_s
    finally:
        link.close()
