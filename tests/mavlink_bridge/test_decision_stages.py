"""The decision step's stages driven on their own, without a network: vehicles known only from
the MAVLink messages they would have sent (parsed by VehicleState's handlers), one step through
gather, plan, envelope, record, command batch and account."""

from __future__ import annotations

import numpy as np

from mavlink_bridge.mission.decision_step import DecisionStep, LoopState
from mavlink_bridge.results.mission_result import MissionAccount
from mavlink_bridge.safety.flight_envelope import FlightEnvelope
from mavlink_bridge.safety.safety_envelope import SafetyEnvelope
from mavlink_bridge.vehicles.flight_prediction import PlaneModel
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_wire.protocol import mavlink
from planner.geodesy import local_km_to_geodetic
from planner.grid import Grid
from planner.hapf_aco import HapfAcoPlanner
from planner.metrics import MissionRecorder


def _heard(
    sysid: int, lat: float, lon: float, time_ms: int, north_cms: int = 0, east_cms: int = 10_000
) -> VehicleState:
    """A vehicle as the daemon knows it after its heartbeat and one position report (flying
    east at 100 m/s, 100 m up, unless its velocity is given)."""
    v = VehicleState(sysid, link=None)  # type: ignore[arg-type]
    mav = mavlink.MAVLink(None, sysid, 1)
    armed = mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    for msg in (
        mav.heartbeat_encode(
            mavlink.MAV_TYPE_FIXED_WING, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, armed, 15,
            mavlink.MAV_STATE_ACTIVE,
        ),
        mav.global_position_int_encode(
            time_ms, int(lat * 1e7), int(lon * 1e7), 100_000, 100_000, north_cms, east_cms, 0, 9000
        ),
    ):  # fmt: skip
        v.handle(mavlink.MAVLink(None).parse_char(msg.pack(mav)))
    return v


def _stages(paper10, vehicles):
    cfg = paper10.config
    cells = SafetyEnvelope.for_scenario(paper10, 1.0, 1.0)
    plane = PlaneModel(speed_mps=cfg.speed_mps)
    return DecisionStep(
        scenario=paper10,
        grid=Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km),
        cell_envelope=cells,
        plane=plane,
        flight_envelope=FlightEnvelope(cells, plane, step_s=cfg.step_s),
        vehicles=vehicles,
        counters=MissionAccount(),
        target_values={t.id: t.value for t in paper10.targets},
    )


def test_one_step_through_every_stage(paper10):
    starts = paper10.starts_for_seed(1)[:3]
    grid = Grid(paper10.config.grid_nx, paper10.config.grid_ny, paper10.config.cell_km)
    # the three planes 2 cells east of their starts, 5 s into their flight
    here = np.array([[s.x_km + 2.0, s.y_km] for s in starts])
    lat, lon = local_km_to_geodetic(here[:, 0], here[:, 1], paper10.origin)
    vehicles = [_heard(i + 1, lat[i], lon[i], 5000) for i in range(3)]
    vehicles[2].lost = True  # lost: inactive to the planner, no command
    stages = _stages(paper10, vehicles)
    planner = HapfAcoPlanner(paper10, starts, 1)
    recorder = MissionRecorder(paper10, starts)
    state = LoopState.start(grid, planner, recorder, starts, [-1, -1, -1])

    inputs = stages.gather(state, 1, looks={})
    assert inputs.active.tolist() == [True, True, False]
    np.testing.assert_allclose(state.positions[:2], here[:2], atol=1e-3)
    assert (state.cells[:2] == grid.cell_of(here[:2])).all()
    assert state.headings[0] == 0 and state.headings[1] == 0  # east, from the velocity
    assert stages.counters.looks_missed == 2  # no camera, no look

    plan = stages.plan(state, inputs)
    assert plan.proposed_cells.shape == (3, 2)
    # the planner judges an engagement from where a plane measures itself, not its cell centre
    np.testing.assert_allclose(planner.beliefs.measured_km[:2], here[:2], atol=1e-3)
    flight = stages.envelope(state, inputs, plan)
    assert flight.aims_km.shape == (3, 2) and np.isfinite(flight.speeds_mps).all()

    stages.record(state, inputs, plan, flight)
    assert recorder.steps == 1
    batch = stages.command_batch(state, inputs, plan, flight)
    moved = [i for i, _, _ in batch.moves]
    assert moved == [0, 1]  # not the lost one
    assert all(c.command == mavlink.MAV_CMD_DO_REPOSITION for _, _, c in batch.moves)
    assert {c.vehicle.system_id for c in batch.speeds} <= {1, 2}

    # vehicle 1 accepts its guided target, vehicle 2 refuses it: one refusal counted
    for cmd in batch.commands:
        result = mavlink.MAV_RESULT_ACCEPTED
        if cmd.vehicle.system_id == 2 and cmd.command == mavlink.MAV_CMD_DO_REPOSITION:
            result = mavlink.MAV_RESULT_DENIED
        mav = mavlink.MAVLink(None, cmd.vehicle.system_id, 1)
        frame = mav.command_ack_encode(cmd.command, result).pack(mav)
        cmd.vehicle.handle(mavlink.MAVLink(None).parse_char(frame))
        cmd.ack = cmd.vehicle.acks[(1, cmd.command)]
    stages.account(state, 1, batch, batch.commands, flight)
    assert state.last_target[0] == batch.moves[0][1] and state.last_target[1] is None
    assert state.refusals == [0, 1, 0] and stages.counters.refused_commands == 1
    assert (state.commanded_cells == flight.next_cells).all()


def test_a_plane_held_in_its_cell_leaves_on_the_course_it_circles_on(paper10):
    """A plane told to hold (its last target was the cell it was in) circles there: the next
    step plans from the course it flies (or the viable one nearest it), not from the heading it
    came in on. Held at the area's corner heading out of it, the commanded heading left it no
    move but another hold, step after step (a PX4 plane stayed in a corner for a whole
    mission). The same at step 0, circling its take-off point."""
    cfg = paper10.config
    grid = Grid(cfg.grid_nx, cfg.grid_ny, cfg.cell_km)
    starts = paper10.starts_for_seed(1)[:1]
    corner = np.array([[cfg.grid_nx - 1, cfg.grid_ny - 1]])
    here = grid.centre_km(corner)
    lat, lon = local_km_to_geodetic(here[:, 0], here[:, 1], paper10.origin)
    # circling there, flying south at this instant
    vehicles = [_heard(1, lat[0], lon[0], 50_000, north_cms=-10_000, east_cms=0)]
    stages = _stages(paper10, vehicles)
    state = LoopState.start(grid, HapfAcoPlanner(paper10, starts, 1),
                            MissionRecorder(paper10, starts), starts, [-1])  # fmt: skip
    northeast, south = 1, 6  # heading indices: counter-clockwise from east in 45 deg steps
    state.cells[:] = corner
    state.commanded_cells[:] = corner  # the last step held it in its cell
    state.commanded_headings[:] = northeast  # the heading it came in on: out of the area
    stages.gather(state, 5, looks={})
    assert state.headings[0] == south
    # circling there flying east, out of the area: it leaves on the viable course nearest that
    stages.vehicles[0] = _heard(1, lat[0], lon[0], 60_000)  # flying east
    state.cells[:] = corner
    state.commanded_cells[:] = corner
    stages.gather(state, 6, looks={})
    east = 0
    assert state.headings[0] != east and stages.cell_envelope.viable(corner[0], state.headings[0])
    assert not stages.cell_envelope.viable(corner[0], east)
    # step 0: circling its take-off point on the south edge, caught flying south (every move
    # within the turn limit leaves the area): it leaves on the viable course nearest south
    edge = np.array([[cfg.grid_nx // 2, 0]])
    lat, lon = local_km_to_geodetic(*grid.centre_km(edge).T, paper10.origin)
    stages.vehicles[0] = _heard(1, lat[0], lon[0], 70_000, north_cms=-10_000, east_cms=0)
    assert not stages.cell_envelope.viable(edge[0], south)
    stages.gather(state, 0, looks={})
    assert state.headings[0] in (5, 7)  # south-west or south-east: on along the edge
    assert stages.cell_envelope.viable(edge[0], state.headings[0])
    # a plane that arrived in its commanded cell from another one flies the heading of that move
    lat, lon = local_km_to_geodetic(here[:, 0], here[:, 1], paper10.origin)
    stages.vehicles[0] = _heard(1, lat[0], lon[0], 80_000)
    state.cells[:] = corner - 1
    state.commanded_cells[:] = corner
    state.commanded_headings[:] = northeast
    stages.gather(state, 7, looks={})
    assert state.headings[0] == northeast


def test_a_vehicle_without_a_camera_gets_one_warning_and_no_more_engagement_requests(paper10):
    """ArduPlane without a camera on any port answers IMAGE_START_CAPTURE for component 100
    itself, FAILED: that vehicle is named once and its engagements are off (never a retry every
    step); a vehicle whose camera was heard (its HEARTBEAT) is only retried."""
    from mavlink_bridge.vehicles.guided_commands import engagement_command

    starts = paper10.starts_for_seed(1)[:2]
    lat, lon = local_km_to_geodetic([s.x_km for s in starts], [s.y_km for s in starts],
                                    paper10.origin)  # fmt: skip
    vehicles = [_heard(i + 1, lat[i], lon[i], 5000) for i in range(2)]
    said: list[str] = []
    stages = _stages(paper10, vehicles)
    stages.say = said.append
    ap, cam = mavlink.MAVLink(None, 1, 1), mavlink.MAVLink(None, 2, 100)
    request = engagement_command(vehicles[0], 1)
    request.attempts = 1

    def wire(msg, mav):  # as the daemon gets it: packed, then parsed
        return mavlink.MAVLink(None).parse_char(msg.pack(mav))

    vehicles[0].handle(  # the autopilot (component 1) answers for the missing camera
        wire(ap.command_ack_encode(mavlink.MAV_CMD_IMAGE_START_CAPTURE, 4), ap)  # FAILED
    )
    assert stages.without_camera(0, request)
    assert stages.counters.cameraless == [0] and len(said) == 1
    assert "vehicle 1 has no camera" in said[0] and "MAV_RESULT_FAILED" in said[0]
    # vehicle 2's camera is there (heard), it just did not answer this time: asked again
    vehicles[1].handle(
        wire(cam.heartbeat_encode(mavlink.MAV_TYPE_CAMERA, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4),
             cam)
    )  # fmt: skip
    unanswered = engagement_command(vehicles[1], 1)
    unanswered.attempts = 5
    assert not stages.without_camera(1, unanswered)
    assert stages.counters.cameraless == [0] and len(said) == 1


def test_a_stale_position_is_flown_on_to_where_the_plane_is_now(paper10):
    """Paced at 20x over a 30 % loss link, a plane's latest position report was 10 s old on its
    clock at a decision: paths predicted from it as if it were now started 1 km behind the
    plane (issue 12: a plane inside a threat's margin). The report is flown on along the way
    to the target the plane last accepted, for as long as the report is old on its clock."""
    starts = paper10.starts_for_seed(1)[:1]
    grid = Grid(paper10.config.grid_nx, paper10.config.grid_ny, paper10.config.cell_km)
    here = np.array([[starts[0].x_km + 2.0, starts[0].y_km]])
    lat, lon = local_km_to_geodetic(here[:, 0], here[:, 1], paper10.origin)
    vehicle = _heard(1, lat[0], lon[0], 5000)  # flying east at 100 m/s
    stages = _stages(paper10, [vehicle])
    state = LoopState.start(
        grid, HapfAcoPlanner(paper10, starts, 1), MissionRecorder(paper10, starts), starts, [-1]
    )
    stages.gather(state, 1, looks={})
    state.last_target[0] = (float(here[0, 0]) + 5.0, float(here[0, 1]))  # 5 km east
    active = np.array([True])
    stages.clock_rate = 20.0
    stages.wall_clock = lambda: vehicle.position_s + 0.5  # 0.5 s of wall time: 10 s of flight
    positions, courses, _, elapsed = stages.where_now(state, active)
    np.testing.assert_allclose(positions[0], here[0] + [1.0, 0.0], atol=0.05)
    assert abs(courses[0]) < 0.05 and elapsed[0] == 10
    stages.predict_from_now = False  # lockstep: the planes wait at the decision instant
    positions, _, _, elapsed = stages.where_now(state, active)
    np.testing.assert_allclose(positions[0], here[0], atol=1e-3)
    assert elapsed[0] == 0


def test_a_uav_counted_home_is_sent_to_circle_its_start_not_where_it_drifted(paper10):
    """A UAV the planner counts as home (``done``) keeps flying: it is sent to circle its start
    cell. Sent to circle the cell it was in at each step, a plane on a 1-2 km turn radius
    drifted a cell or more a step (lockstep demo, paper-10uav seed 2: 1 of 10 within a cell of
    its start at the end, 10 of 10 offline)."""
    starts = paper10.starts_for_seed(1)[:2]
    grid = Grid(paper10.config.grid_nx, paper10.config.grid_ny, paper10.config.cell_km)
    here = np.array([[s.x_km + 2.0, s.y_km] for s in starts])  # drifted 2 cells east
    lat, lon = local_km_to_geodetic(here[:, 0], here[:, 1], paper10.origin)
    stages = _stages(paper10, [_heard(i + 1, lat[i], lon[i], 5000) for i in range(2)])
    planner = HapfAcoPlanner(paper10, starts, 1)
    recorder = MissionRecorder(paper10, starts)
    state = LoopState.start(grid, planner, recorder, starts, [-1, -1])
    inputs = stages.gather(state, 1, looks={})
    planner.beliefs.done[0] = True  # UAV 1 is back; UAV 2 still searching
    plan = stages.plan(state, inputs)
    home = grid.cell_of(np.array([[starts[0].x_km, starts[0].y_km]]))[0]
    np.testing.assert_array_equal(plan.proposed_cells[0], home)
    flight = stages.envelope(state, inputs, plan)
    np.testing.assert_array_equal(flight.next_cells[0], home)
    np.testing.assert_allclose(flight.aims_km[0], grid.centre_km(home))
    assert not np.array_equal(plan.proposed_cells[1], home)
