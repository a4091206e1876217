"""Separation without a centre, flown (mavlink_bridge/safety/neighbour_flights.py): a planner
node's flight envelope predicts its neighbours' flights from what they said on the swarm link
(state with course and ground speed, claimed cell) and keeps its own plane's flight apart from
them as the central envelope keeps each pair apart.

The geometry (paper-10uav, clear of its threats): UAV 0 at cell (18, 30) flying east claims
(19, 29), turning right; UAV 1 at (20, 30) flying north-west claims (19, 31), straight on. The
claimed cells are 2 km apart (d_min 1 km + the planner's 1 km margin), but the two curved flights
between the cells close to well inside d_min + the predicted margin mid-step."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mavlink_bridge.mission.context import MissionContext
from mavlink_bridge.mission.options import DaemonOptions
from mavlink_bridge.safety.flight_envelope import FlightChoice
from mavlink_bridge.safety.neighbour_flights import HeardFlight, neighbour_flights
from mavlink_bridge.vehicles.flight_prediction import predict_paths
from mavlink_wire.node_wire import NodeWire
from mavlink_wire.swarm_wire import decode_report, encode_report
from planner.grid import HEADING_STEPS
from planner.scenario import load_scenario
from planner.swarm_messages import CellClaim, UavState

CELLS = np.array([[18, 30], [20, 30]])
HEADINGS = np.array([0, 3])
CLAIMS = np.array([[19, 29], [19, 31]])
CLAIM_HEADINGS = np.array([7, 3])
SPEED_MPS = 100.0


def _context(fleet: tuple[int, ...], lockstep: bool) -> MissionContext:
    options = DaemonOptions(connect=["udpin:127.0.0.1:0"], fleet=fleet, lockstep=lockstep)
    return MissionContext(load_scenario("paper-10uav"), options)


def _previous_aims(ctx: MissionContext) -> np.ndarray:
    """The target each plane flew to at the decision instant: its last leg's, straight on."""
    env = ctx.envelope
    return np.array([env.aim_point_km(c - HEADING_STEPS[h], c, 1.0)
                     for c, h in zip(CELLS, HEADINGS, strict=True)])  # fmt: skip


def _choose(ctx: MissionContext, uavs: list[int], neighbours=None) -> FlightChoice:
    """The envelope of ``ctx`` over ``uavs`` (of the two), at their decision instant."""
    cells, heads = CELLS[uavs], HEADINGS[uavs]
    positions = ctx.grid.centre_km(cells)
    return ctx.flight_envelope.choose(
        positions, heads * math.pi / 4, np.full(len(uavs), SPEED_MPS), cells, heads,
        CLAIMS[uavs], CLAIM_HEADINGS[uavs], _previous_aims(ctx)[uavs], np.zeros(len(uavs)),
        positions.copy(), np.ones(len(uavs), dtype=bool), 1.0, neighbours=neighbours,
    )  # fmt: skip


def _heard_over_the_wire(
    ctx: MissionContext, uav: int, claim: bool = True, row: int = 0
) -> HeardFlight:
    """What a node hears of neighbour ``uav`` flying as ``row`` of the geometry: its state and
    claim through the swarm link's encoding and back."""
    wire = NodeWire.for_scenario(ctx.scenario)
    centre = ctx.grid.centre_km(CELLS[row])
    state = UavState(uav, 12, tuple(CELLS[row]), int(HEADINGS[row]), (centre[0], centre[1]),
                     5.0, True, HEADINGS[row] * math.pi / 4, SPEED_MPS)  # fmt: skip
    said = [state] + ([CellClaim(uav, 12, tuple(CLAIMS[row]), int(CLAIM_HEADINGS[row]), ())]
                      if claim else [])  # fmt: skip
    heard = wire.messages(decode_report(encode_report(wire.report(uav, 12, said))))
    s = next(m for m in heard if isinstance(m, UavState))
    c = next((m for m in heard if isinstance(m, CellClaim)), None)
    leg = (tuple(CELLS[row] - HEADING_STEPS[HEADINGS[row]]), tuple(CELLS[row]))
    return HeardFlight(uav, 0, s.position_km, s.course_rad, s.speed_mps, s.cell, s.heading,
                       s.flying, None if c is None else c.cell,
                       0 if c is None else c.heading, leg, s.position_km)  # fmt: skip


def _node_neighbours(ctx: MissionContext, heard: list[HeardFlight], own: int = 1):
    fe = ctx.flight_envelope
    return neighbour_flights(heard, own, ctx.envelope, fe.model, fe.step_s, 1.0, 0.0)


def _need_km(ctx: MissionContext) -> float:
    return ctx.envelope.min_separation_km + ctx.flight_envelope.separation_margin_km


def test_claims_apart_whose_flights_cross_mid_step_make_the_node_override() -> None:
    ctx = _context((1,), lockstep=False)
    apart = np.hypot(*(ctx.grid.centre_km(CLAIMS[0]) - ctx.grid.centre_km(CLAIMS[1])))
    assert apart >= ctx.envelope.min_separation_km + ctx.envelope.separation_margin_km
    heard = _heard_over_the_wire(ctx, 0)
    assert heard.course_rad == pytest.approx(0.0) and heard.speed_mps == SPEED_MPS
    neighbours = _node_neighbours(ctx, [heard])
    assert neighbours is not None and len(neighbours) == 1
    # the two flights as predicted: they come within d_min + the margin mid-step
    fe = ctx.flight_envelope
    alone = _choose(ctx, [1])
    assert alone.overrides["predicted_separation"] == 0
    assert np.array_equal(alone.next_cells[0], CLAIMS[1])  # alone, its claim is flown
    starts = np.concatenate([ctx.grid.centre_km(CELLS[1:]), neighbours.positions_km])
    paths = predict_paths(fe.model, starts, np.array([HEADINGS[1] * math.pi / 4,
                                                      neighbours.courses_rad[0]]),
                          np.concatenate([alone.aims_km, neighbours.aims_km]), 15.0,
                          speed_mps=SPEED_MPS, commanded_mps=np.array([alone.speeds_mps[0],
                                                                       SPEED_MPS]))  # fmt: skip
    closest = np.hypot(*(paths[0] - paths[1]).T)
    assert closest.min() < _need_km(ctx) and closest.argmin() > 0  # mid-step, not now
    # with the neighbour's flight, the node's envelope replaces its cell and keeps apart
    kept = _choose(ctx, [1], neighbours)
    assert kept.overrides["predicted_separation"] == 1
    assert kept.replaced == [(0, "predicted_separation")]
    assert not np.array_equal(kept.next_cells[0], CLAIMS[1])
    assert kept.min_separation_km >= _need_km(ctx)


@pytest.mark.parametrize("lockstep", [True, False])
def test_each_node_decides_what_the_central_envelope_decides_for_the_pair(lockstep) -> None:
    central = _choose(_context((0, 1), lockstep), [0, 1])
    assert central.overrides["predicted_separation"] == 1
    for own, other in ((1, 0), (0, 1)):
        ctx = _context((own,), lockstep)
        heard = _heard_over_the_wire(ctx, other, row=other)
        node = _choose(ctx, [own], _node_neighbours(ctx, [heard], own))
        assert np.array_equal(node.next_cells[0], central.next_cells[own])
        assert node.next_headings[0] == central.next_headings[own]
        assert np.allclose(node.aims_km[0], central.aims_km[own], atol=1e-9)
        assert node.speeds_mps[0] == pytest.approx(central.speeds_mps[own])
        assert node.replaced == [(0, r) for i, r in central.replaced if i == own]


def test_a_neighbour_whose_claim_was_lost_flies_on_and_is_kept_apart_from() -> None:
    ctx = _context((1,), lockstep=False)
    # UAV 2 flies as UAV 0 did: with its claim heard, it settles after node 1's plane, as the
    # central daemon flying UAVs 1 and 2 settles them
    heard = _node_neighbours(ctx, [_heard_over_the_wire(ctx, 2)])
    assert heard is not None and heard.free[0]
    first = _choose(ctx, [1], heard)
    central = _choose(_context((1, 2), lockstep=False), [1, 0])
    assert np.array_equal(first.next_cells[0], central.next_cells[0])
    assert np.allclose(first.aims_km[0], central.aims_km[0], atol=1e-9)
    # a cell further west, its claim lost: it flies on east to its last target (a leg ahead),
    # and node 1's plane, which alone would fly its claim, keeps apart from that
    lost = dataclasses.replace(_heard_over_the_wire(ctx, 2, claim=False), position_km=(17.5, 30.5),
                               cell=(17, 30), flown_leg=((16, 30), (17, 30)))  # fmt: skip
    silent = _node_neighbours(ctx, [lost])
    assert silent is not None and not silent.free[0]
    assert np.allclose(silent.aims_km[0], ctx.envelope.aim_point_km((16, 30), (17, 30), 1.0))
    assert _choose(ctx, [1]).overrides["predicted_separation"] == 0
    kept = _choose(ctx, [1], silent)
    assert kept.overrides["predicted_separation"] == 1
    assert kept.min_separation_km >= _need_km(ctx)
    assert kept.min_separation_lossy_km >= _need_km(ctx)


def test_a_neighbour_not_heard_this_step_is_its_last_state_advanced() -> None:
    ctx = _context((1,), lockstep=False)
    heard = _heard_over_the_wire(ctx, 0)
    fe = ctx.flight_envelope
    older = HeardFlight(**{**heard.__dict__, "age_steps": 1})
    flights = neighbour_flights([older], 1, ctx.envelope, fe.model, fe.step_s, 1.0, 2.0)
    assert flights is not None and not flights.free[0]
    # it flew on for a period and 2 s to its claimed target of then, and flies on to it
    aim = ctx.envelope.aim_point_km(CELLS[0], CLAIMS[0], 1.0)
    assert np.allclose(flights.aims_km[0], aim) and np.allclose(flights.previous_aims_km[0], aim)
    flown = np.hypot(*(flights.positions_km[0] - ctx.grid.centre_km(CELLS[0])))
    assert 0.9 * (fe.step_s + 2.0) * SPEED_MPS / 1e3 < flown <= (fe.step_s + 2.0) * SPEED_MPS / 1e3
    # far away, it is not one to keep apart from
    here = ctx.grid.centre_km(CELLS[1])
    assert neighbour_flights([older], 1, ctx.envelope, fe.model, fe.step_s, 1.0, 2.0, here,
                             fe.separation_reach_km) is not None  # fmt: skip
    assert neighbour_flights([older], 1, ctx.envelope, fe.model, fe.step_s, 1.0, 2.0,
                             here + 40.0, fe.separation_reach_km) is None  # fmt: skip
