"""Grid, topology, potential field, pheromone, constraints and transition rules."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from planner.config import ConfigError, PlannerConfig
from planner.constraints import SafetyModel, segment_clearance
from planner.grid import (
    Grid,
    candidate_moves,
    corridor_offsets,
    disc_overlap,
    heading_change_deg,
    steps_to_reach,
)
from planner.pheromone import PheromoneMaps
from planner.potential_field import attraction, morse_repulsion, threat_repulsion
from planner.scenario import load_scenario
from planner.topology import adapt_radius, adjacency, pairwise_distances
from planner.transition import claim_cells, heuristic_choice, use_deterministic
from sim_gateway.offline_runner import run_offline

CFG = PlannerConfig()
GRID = Grid()


@given(st.integers(0, 99), st.integers(0, 99), st.integers(0, 7))
def test_no_candidate_cell_violates_the_turn_limit(x, y, h):
    cells, headings = candidate_moves(np.array([[x, y]]), np.array([h]), 45.0)
    assert cells.shape == (1, 3, 2)
    assert np.all(heading_change_deg(h, headings[0]) <= 45.0)
    steps = np.abs(cells[0] - [x, y])
    assert np.all(steps.max(axis=1) == 1)  # one cell per step


def test_footprint_of_radius_3_has_29_cells():
    assert len(GRID.disc_offsets(3.0)) == 29


def test_adjacency_and_radius_adaptation_follow_eqs_1_to_3():
    pos = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 10.0], [40.0, 40.0]])
    d = pairwise_distances(pos)
    a = adjacency(d, np.array([5.0, 5.0, 5.0, 5.0]), np.ones(4, bool))
    assert a[0, 1] and a[1, 0] and not a[0, 2] and not a[0, 0] and not a[3].any()
    cfg = CFG.replace(n_topo=2, topology_rate=0.1, sensing_radius_km=50.0)
    r = adapt_radius(np.array([5.0, 5.0]), np.array([0, 4]), cfg)
    assert r[0] == pytest.approx(5.0 + 0.1 * 50 * 1.0)  # too few neighbours: grow
    assert r[1] == pytest.approx(max(5.0 - 0.1 * 50 * 1.0, cfg.coop_radius_min_km))
    assert adapt_radius(np.array([49.0]), np.array([0]), cfg)[0] == 50.0  # capped by R_sen


def test_attraction_points_up_the_tpm_gradient():
    patch = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.5, 0.5, 0.5]])  # grows with x
    f = attraction(patch[None], CFG)[0]
    assert f[0] == pytest.approx(0.2) and f[1] == pytest.approx(0.0)


def test_threat_repulsion_grows_toward_the_threat_and_vanishes_outside():
    threat = np.array([[50.0, 50.0]])
    radius = np.array([4.0])
    pts = np.array([[[55.0, 50.0], [56.0, 50.0], [60.0, 50.0]]])
    f = threat_repulsion(pts, threat, radius, np.array([[True]]), CFG)[0]
    assert f[0, 0] > f[1, 0] > 0  # away from the centre (+x), stronger closer
    assert f[2, 0] == 0  # beyond R_t + R
    unknown = threat_repulsion(pts, threat, radius, np.array([[False]]), CFG)
    assert np.all(unknown == 0)


def test_morse_repulsion_matches_eq27():
    cfg = CFG
    others = np.array([[0.0, 0.0], [2.0, 0.0]])
    points = others[:, None, :]  # each UAV's force at its own position
    f = morse_repulsion(points, others, np.array([[False, True], [True, False]]), cfg)[0, 0]
    d, c, b, r0 = 2.0, cfg.morse_c_km, cfg.morse_b, cfg.morse_r0_km
    expected = (b / c) * np.exp(d / c) / (np.exp(d / c) - np.exp(r0 / c)) ** 2
    assert f[0] == pytest.approx(-expected) and f[1] == pytest.approx(0.0)


def test_pheromone_stays_clamped_and_follows_eqs_32_to_34():
    cfg = CFG
    ph = PheromoneMaps(2, cfg)
    for _ in range(40):
        ph.local_update(np.array([0, 0]), np.array([[50, 50], [51, 50]]))
    assert ph.tau.min() >= cfg.tau_min and ph.tau.max() <= cfg.tau_max
    assert ph.tau[0, 50, 50] == cfg.tau_min and ph.tau[1, 50, 50] == cfg.tau_max
    ph2 = PheromoneMaps(1, cfg)
    ph2.local_update(np.array([0]), np.array([[20, 20]]))
    assert ph2.tau[0, 20, 20] == pytest.approx(cfg.tau_max - cfg.local_decrement)
    assert ph2.tau[0, 22, 20] == pytest.approx(cfg.tau_max - cfg.local_decrement * (81 - 16) / 81)
    assert ph2.tau[0, 24, 20] == cfg.tau_max  # beyond R
    ph2.global_update()
    assert ph2.tau[0, 20, 20] == cfg.tau_max  # raised by F * dtau_g0 = 0.3, clamped


def test_viability_never_lets_a_uav_into_a_threat_or_out_of_the_area():
    threats = np.array([[50.0, 50.0], [20.0, 80.0]])
    radii = np.array([6.0, 3.0])
    model = SafetyModel(GRID, threats, radii, 0.0, 45.0)
    rng = np.random.default_rng(3)
    for _ in range(20):  # random walks over allowed moves from viable states stay safe for ever
        while True:
            cell = rng.integers(0, 100, 2)
            h = int(rng.integers(0, 8))
            if model.viable[h, cell[0], cell[1]]:
                break
        for _ in range(300):
            cand, heads = candidate_moves(cell[None], np.array([h]), 45.0)
            ok = model.move_allowed(np.repeat(cell[None], 3, 0), heads[0])
            assert ok.any(), "a viable state always has an allowed move"
            k = rng.choice(np.flatnonzero(ok))
            clearance = segment_clearance(
                GRID.centre_km(cell), GRID.centre_km(cand[0, k]), threats, radii
            )
            assert clearance > 0 and GRID.inside(cand[0, k])
            cell, h = cand[0, k], int(heads[0, k])


def test_distance_home_goes_around_threats():
    model = SafetyModel(GRID, np.array([[50.0, 50.0]]), np.array([10.0]), 0.0, 45.0)
    home = GRID.flat(np.array([30, 50]))
    d = model.distance_home_km(int(home))
    assert d[30, 50] == 0
    assert d[70, 50] > 40.0 + 1.0  # straight line 40 km goes through the threat
    free = SafetyModel(GRID, np.zeros((0, 2)), np.zeros(0), 0.0, 45.0).distance_home_km(int(home))
    assert free[70, 50] == pytest.approx(40.0)


def test_the_way_home_can_be_counted_wider_of_the_threats_than_the_moves():
    """``home_margin_km``: the way home is counted clear of the threats by a wider margin (the
    daemon's flight envelope keeps its planes' loiter circles that far off), the moves and
    their viability keep the planner's own."""
    threat, radius = np.array([[50.0, 50.0]]), np.array([10.0])
    home = int(GRID.flat(np.array([30, 50])))
    tight = SafetyModel(GRID, threat, radius, 0.0, 45.0)
    wide = SafetyModel(GRID, threat, radius, 0.0, 45.0, home_margin_km=2.5)
    assert np.array_equal(wide.edge_safe, tight.edge_safe)
    assert np.array_equal(wide.viable, tight.viable)
    # across the threat the way round is longer; in the open the same
    assert wide.distance_home_km(home)[70, 50] > tight.distance_home_km(home)[70, 50] + 2.0
    assert wide.distance_home_km(home)[30, 80] == tight.distance_home_km(home)[30, 80]
    # never fewer moves home (diagonal moves count one: here round the threat costs none)
    x, y = np.meshgrid(np.arange(GRID.nx), np.arange(GRID.ny), indexing="ij")
    x, y, homes = x[None], y[None], np.array([home])
    heading = np.zeros(x.shape, dtype=np.int64)
    hops_wide = wide.hops_home_at(homes, x, y, heading)
    hops_tight = tight.hops_home_at(homes, x, y, heading)
    assert np.all(hops_wide >= hops_tight)
    # a UAV already inside the wider band still has a way home (by the planner's own moves)
    assert np.isfinite(wide.distance_home_km(home)[50, 61])


def test_the_way_home_is_counted_in_turn_limited_moves_and_searched_only_when_time_is_near():
    """``hops_home_at`` counts the turn-limited moves home over (heading, cell) states. The
    count in cell moves plus the turns onto the first (``_cell_hops``) stands in for it while a
    UAV has ``HOP_SEARCH_SLACK`` steps to spare: over paper-10uav's threats, homes every 11
    cells and every cell and heading, the turn-limited way is at most 10 steps longer, so the
    stand-in never lets a move through that the search would refuse."""
    from planner.constraints import HOP_SEARCH_SLACK

    scenario = load_scenario("paper-10uav")
    threats = np.array([[t.x_km, t.y_km] for t in scenario.threats])
    radii = np.array([t.radius_km for t in scenario.threats])
    model = SafetyModel(GRID, threats, radii, 0.0, 45.0)
    x, y, h = np.meshgrid(np.arange(GRID.nx), np.arange(GRID.ny), np.arange(8), indexing="ij")
    x, y, h = x[None], y[None], h[None]
    longest = 0.0
    for hx in range(5, 100, 11):
        for hy in range(5, 100, 11):
            home = np.array([GRID.flat(np.array([hx, hy]))])
            exact = model.hops_home_at(home, x, y, h)
            cells = model._cell_hops(home, x, y, h)
            both = np.isfinite(exact) & np.isfinite(cells)
            longest = max(longest, float((exact[both] - cells[both]).max()))
    assert 0 < longest <= HOP_SEARCH_SLACK / 2, longest
    # the UAV whose time is near gets the search (bounded by its time), the others the stand-in
    home = np.array([GRID.flat(np.array([40, 40]))] * 2)
    cells = np.array([[40 + 15], [40 + 55]]), np.array([[40], [40]]), np.array([[0], [0]])
    fresh = SafetyModel(GRID, threats, radii, 0.0, 45.0)  # nothing searched yet
    searched = fresh.hops_home_at(home, *cells, within=30)
    assert searched[0, 0] == model.hops_home_at(home[:1], *(c[:1] for c in cells))[0, 0]
    assert searched[1, 0] == model._cell_hops(home[1:], *(c[1:] for c in cells))[0, 0]
    # searched up to 30 + HOP_SEARCH_SLACK steps: further is inf until asked for all of it
    far = np.array([[95]]), np.array([[95]]), np.array([[0]])
    assert not np.isfinite(fresh._state_hops(home[:1], *far, within=30)[0, 0])
    assert fresh.hops_home_at(home[:1], *far)[0, 0] == model.hops_home_at(home[:1], *far)[0, 0]


def test_deterministic_switch_and_heuristic_choice():
    q = np.array([0.1, 0.9, 0.1])
    det = use_deterministic(np.array([1.0, 1.0, 1e-9]), np.array([1.0, 1.0, 1e-9]), q, CFG)
    assert det.tolist() == [True, False, False]  # flat field: never deterministic
    w = np.array([[0.0, 1.0, 3.0], [0.0, 1.0, 0.0]])
    greedy = heuristic_choice(w, np.array([0.0, 0.0]), np.array([0.5, 0.5]), CFG)
    assert greedy.tolist() == [2, 1]
    draws = [
        heuristic_choice(w[:1], np.array([1.0]), np.array([u]), CFG)[0]
        for u in np.linspace(0, 0.999, 200)
    ]
    assert 0 not in draws  # a forbidden cell is never drawn
    assert abs(np.mean(np.array(draws) == 2) - 0.75) < 0.02  # eq 36 probabilities


def test_claim_cells_keeps_min_separation():
    cand = np.array([[[10, 10], [11, 10], [12, 10]], [[10, 10], [10, 11], [10, 12]]])
    ranked = np.array([[0, 1, 2], [0, 1, 2]])
    pos = np.array([[9.5, 10.5], [10.5, 9.5]])
    pick = claim_cells(ranked, cand, np.ones((2, 3), bool), pos, np.ones(2, bool), 1.0, 1.0, 3.0)
    assert pick.tolist() == [0, 1]


def test_a_uav_left_without_a_separated_move_gets_one_freed_by_the_uav_before_it():
    # A and B may each go to X; B's other move is the cell of C, which holds still. A claims
    # first (equal choice, lower index) and takes X, its first choice: B would have had to
    # follow it into X. A has another allowed move, Y, so A takes Y and B takes X.
    x, y, c_cell = [12, 11], [13, 13], [10, 10]
    cand = np.array([[x, y, [0, 0]], [x, c_cell, [0, 0]], [c_cell, c_cell, c_cell]])
    allowed = np.array([[True, True, False], [True, True, False], [True, True, True]])
    ranked = np.array([[0, 1, 2], [0, 1, 2], [0, 1, 2]])
    pos = np.array([[12.5, 12.5], [11.5, 11.5], [10.5, 10.5]])
    movers = np.array([True, True, False])
    pick = claim_cells(ranked, cand, allowed, pos, movers, 1.0, 1.0, 3.0)
    assert pick[:2].tolist() == [1, 0]
    spots = cand[[0, 1], pick[:2]] + 0.5
    assert np.hypot(*(spots[0] - spots[1])) >= 1.0


def test_the_swap_never_moves_a_uav_that_holds_still():
    # A may only go to X; B's other move is the cell of C, which holds still and would have a
    # free cell far off were it moving: C is not moved for B, and B's breach stays visible
    x, c_cell, far = [12, 11], [10, 10], [20, 20]
    cand = np.array([[x, x, x], [x, c_cell, [0, 0]], [c_cell, far, far]])
    allowed = np.array([[True, False, False], [True, True, False], [True, True, True]])
    ranked = np.array([[0, 1, 2], [1, 0, 2], [0, 1, 2]])
    pos = np.array([[12.5, 12.5], [11.5, 11.5], [10.5, 10.5]])
    pick = claim_cells(ranked, cand, allowed, pos, np.array([True, True, False]), 1.0, 1.0, 3.0)
    assert pick[2] == 0  # C's row is untouched
    assert pick[0] == 0  # A has nowhere else to go: B's breach stays visible (its first choice)
    assert pick[1] == 1


def test_paper_10uav_seed_14_keeps_its_uavs_apart_where_the_greedy_claim_did_not():
    # with pursue_threshold 0.1, two UAVs beside a threat both took one cell at step 193: the
    # first to claim had another move, the second had none left
    scenario = load_scenario("paper-10uav").with_config(pursue_threshold=0.1)
    result = run_offline(scenario, 14, account=False)
    assert result["violations"]["separation"] == 0
    assert result["min_separation_km"] >= scenario.config.min_separation_km


def test_config_rejects_bad_values_with_a_clear_message():
    with pytest.raises(ConfigError, match="p_detect"):
        PlannerConfig(p_detect=1.5)
    with pytest.raises(ConfigError, match="tau_min"):
        PlannerConfig(tau_min=2.0)


def test_corridor_weights_the_footprints_ahead_and_leaves_out_the_candidates_own():
    footprint = GRID.disc_offsets(3.0)
    offsets, weights = corridor_offsets(footprint, steps=4, discount=0.5)
    east = {tuple(o): w for o, w in zip(offsets[0], weights[0], strict=True) if w > 0}
    assert (0, 0) not in east and (3, 0) not in east  # in the candidate's own footprint
    assert east[(4, 0)] == pytest.approx(0.5) and east[(5, 0)] == pytest.approx(0.25)
    assert east[(6, 0)] == pytest.approx(0.125) and (7, 0) not in east
    north = {tuple(o) for o, w in zip(offsets[2], weights[2], strict=True) if w > 0}
    assert north == {(-y, x) for x, y in east}  # the same corridor turned by 90 degrees


def test_disc_overlap_shares_sum_to_the_disc_area():
    offsets, shares = disc_overlap(1.0, 1.0, samples=64)
    assert shares.sum() == pytest.approx(np.pi, rel=2e-3)
    own = shares[(offsets == 0).all(axis=1)][0]
    assert own == pytest.approx(1.0)  # a 1 km disc covers its own 1 km cell entirely
    side = shares[(offsets == [1, 0]).all(axis=1)][0]
    assert 0.3 < side < 0.5


def test_freedom_counts_the_ways_on_and_is_one_in_a_corner():
    model = SafetyModel(GRID, np.zeros((0, 2)), np.zeros(0), 0.0, 45.0)
    assert model.freedom[0, 50, 50] == 3  # open sky: left, straight, right
    # heading east one cell from the east edge: only the turn that stays inside and viable
    assert model.freedom[0, 98, 50] < 3
    assert (model.freedom >= 1)[model.viable].all()  # a viable state always has a way on


def test_steps_to_reach_counts_the_detour_around_the_turning_circle():
    steps = steps_to_reach(45.0, 6)
    r = 6
    assert steps[0, r, r] == 0 and steps[0, r + 3, r] == 3  # straight ahead
    assert steps[0, r + 1, r + 1] == 1  # 45 degrees left is one move
    behind = steps[0, r - 1, r]  # the cell just behind needs a loop: at least 5 moves
    assert behind >= 5
    beside = steps[0, r, r + 1]  # the cell alongside: inside the turning circle, more than 1
    assert beside > 1
    # every heading sees the same table turned: east's ahead is north's ahead
    assert steps[2, r, r + 3] == 3
