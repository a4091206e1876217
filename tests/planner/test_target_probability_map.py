import numpy as np
import pytest
from scipy import ndimage

from planner.config import PlannerConfig
from planner.grid import Grid
from planner.motion_forecast import (
    DISTINCT_MIN_CELLS,
    SquareStencil,
    box_cells,
    convolve_reflect,
    distinct_maps,
    ring_kernel,
    shift_with_reflection,
    union_box,
    wiener_kernel_1d,
)
from planner.scenario import TargetSpec
from planner.sensor_model import bayes_update, detection_probability
from planner.target_priors import (
    normalised,
    ring_prior,
    shifted_prior,
    uniform_prior,
    wiener_prior,
)
from planner.target_probability_map import TargetProbabilityMaps

CFG = PlannerConfig()
GRID = Grid()


def test_uniform_prior_is_eq9_and_sums_to_one():
    prior = uniform_prior(GRID)
    assert prior.shape == (100, 100)
    assert np.allclose(prior, 1e-4)
    assert prior.sum() == pytest.approx(1.0)


def test_wiener_prior_has_the_eq11_variance():
    t = TargetSpec(1, "known_position", 50.0, 50.0, 1.0)
    p = normalised(wiener_prior(t, CFG, GRID))
    x = GRID.centres_x_km
    mean_x = (p.sum(axis=1) * x).sum()
    var_x = (p.sum(axis=1) * (x - mean_x) ** 2).sum()
    expected = CFG.delta_0_km**2 + CFG.delta_e_km_per_sqrt_s**2 * CFG.t0_s + 1 / 12  # + cell width
    assert mean_x == pytest.approx(50.0, abs=1e-6)
    assert var_x == pytest.approx(expected, rel=0.01)


def test_ring_prior_of_eq13_peaks_on_the_ring_of_radius_v_t0():
    cfg = CFG.replace(delta_0_km=1.0)  # a sharp prior makes the ring visible
    t = TargetSpec(5, "known_speed", 50.0, 50.0, 1.0, speed_mps=200.0)  # v t0 = 10 km
    p = ring_prior(t, cfg, GRID)
    x, y = np.meshgrid(GRID.centres_x_km, GRID.centres_y_km, indexing="ij")
    r = np.hypot(x - 50, y - 50)
    assert abs(r[np.unravel_index(np.argmax(p), p.shape)] - 10.0) < 1.0
    on_ring = p[np.abs(r - 10) < 0.5].mean()
    assert on_ring > 20 * p[r < 3].mean()  # the centre is nearly empty


def test_shifted_prior_of_eq14_is_centred_at_x_plus_v_t0():
    t = TargetSpec(9, "known_velocity", 30.0, 30.0, 1.0, speed_mps=100.0, heading_rad=np.pi / 2)
    p = normalised(shifted_prior(t, CFG, GRID))
    mean_y = (p.sum(axis=0) * GRID.centres_y_km).sum()
    assert mean_y == pytest.approx(30.0 + 0.1 * CFG.t0_s, abs=0.05)


def test_negative_look_lowers_the_cell_by_the_eq18_ratio():
    p = 0.2
    post = bayes_update(np.array([p]), np.array([False]), 0.9, 0.1)[0]
    assert post == pytest.approx((1 - 0.9) * p / (1 - 0.1 + (0.1 - 0.9) * p))
    post_pos = bayes_update(np.array([p]), np.array([True]), 0.9, 0.1)[0]
    assert post_pos == pytest.approx(0.9 * p / (0.1 + 0.8 * p))
    assert post < p < post_pos


@pytest.mark.parametrize("per_look", [True, False])
def test_detection_probability_follows_eq17(per_look):
    cfg = CFG.replace(sensor_d_in_km=1.0, false_alarm_per_look=per_look)
    floor = cfg.cell_false_alarm
    d = np.array([0.0, cfg.sensor_d_in_km, 2.0, cfg.detection_radius_km, 10.0])
    p = detection_probability(d, cfg)
    assert p[0] == p[1] == cfg.p_detect
    assert p[2] == pytest.approx(cfg.p_detect - (cfg.p_detect - floor) * 0.5)
    assert p[3] == pytest.approx(floor) and p[4] == floor


def test_a_looks_false_alarm_probability_is_p_f_and_a_cells_its_share():
    # eq 17's b_k is one bit for the FOV: the K = 29 cells of a 3 km footprint false-alarm
    # together with P_F; with false_alarm_per_look off, each cell does
    assert CFG.footprint_cells == len(GRID.disc_offsets(CFG.detection_radius_km)) == 29
    together = 1.0 - (1.0 - CFG.cell_false_alarm) ** CFG.footprint_cells
    assert together == pytest.approx(CFG.p_false)
    assert CFG.replace(false_alarm_per_look=False).cell_false_alarm == CFG.p_false


def test_maps_sum_to_target_counts_after_looks_and_forecasts():
    targets = (
        TargetSpec(1, "known_position", 20, 20, 3),
        TargetSpec(2, "known_speed", 50, 50, 2, speed_mps=40),
        TargetSpec(3, "known_velocity", 70, 30, 1, speed_mps=30, heading_rad=1.0),
        TargetSpec(4, "unknown_position", 10, 90, 1),
        TargetSpec(5, "unknown_position", 90, 10, 1),
    )
    tpm = TargetProbabilityMaps(targets, CFG, n_uavs=3)
    rng = np.random.default_rng(0)
    offsets = GRID.disc_offsets(CFG.detection_radius_km)
    for _ in range(30):
        centres = rng.integers(5, 95, size=(3, 2))
        looks = [c + offsets for c in centres]
        tpm.apply_looks(
            np.arange(3), looks, [rng.random(len(offsets)) < 0.1 for _ in looks], centres
        )
        tpm.renormalise()
        tpm.forecast()
    for uav in range(3):
        sums = [tpm.layer_map(l, uav).sum() for l in range(len(tpm.specs))]
        assert sums == pytest.approx(
            [1, 1, 1, 2], rel=1e-4
        )  # (ring, shift, wiener, uniform) counts
        e = tpm.existence_map(uav)
        assert np.all((e >= 0) & (e <= 1))


def test_negative_looks_move_mass_out_of_the_footprint():
    targets = (TargetSpec(1, "unknown_position", 50, 50, 1),)
    tpm = TargetProbabilityMaps(targets, CFG, n_uavs=1)
    cells = np.array([[50, 50]]) + GRID.disc_offsets(CFG.detection_radius_km)
    before = tpm.existence_at(np.zeros(len(cells), int), cells).sum()
    tpm.apply_looks(np.array([0]), [cells], [np.zeros(len(cells), bool)], np.array([[50, 50]]))
    tpm.renormalise()
    assert tpm.existence_at(np.zeros(len(cells), int), cells).sum() < 0.6 * before
    assert tpm.layer_map(0, 0).sum() == pytest.approx(1.0, rel=1e-5)


def test_forecast_kernels_conserve_mass_and_spread():
    k = wiener_kernel_1d(0.63)
    assert k.sum() == pytest.approx(1.0) and np.allclose(k, k[::-1])
    ring = ring_kernel(0.5)
    assert ring.sum() == pytest.approx(1.0)
    maps = np.zeros((2, 20, 20), np.float32)
    maps[:, 0, 0] = 1.0
    maps[1, 10, 10] = 1.0
    out = convolve_reflect(maps, ring)
    assert out.sum(axis=(1, 2)) == pytest.approx(maps.sum(axis=(1, 2)), rel=1e-6)
    assert out[1, 10, 10] == pytest.approx(ring[1, 1])
    # the stencil is the convolution with reflected edges that scipy computes
    reference = ndimage.convolve(maps.astype(np.float64), ring[None], mode="reflect")
    assert np.allclose(out, reference, atol=1e-7)


def test_shift_with_reflection_folds_mass_at_the_edge():
    maps = np.arange(10, dtype=float)[None, :, None] * np.ones((1, 10, 3))
    moved = shift_with_reflection(maps, 3, axis=1)
    assert moved.sum() == pytest.approx(maps.sum())
    assert moved[0, 3, 0] == 0.0 and moved[0, 9, 0] == 6.0 + 7.0  # 6 moved in, 7 folded back
    back = shift_with_reflection(maps, -2, axis=1)
    assert back.sum() == pytest.approx(maps.sum())
    assert back[0, 0, 0] == 2.0 + 1.0


def _track_with_exact_looks(velocity_cells, start_km, steps, cfg):
    """A known-velocity target flown exactly as the world moves it (reflected at the edges),
    looked at every step over the 5 x 5 cells around it with a perfect detection at its true
    cell; returns the TPM and where the target is at the end."""
    speed = np.hypot(*velocity_cells) * 1000 / cfg.step_s
    heading = float(np.arctan2(velocity_cells[1], velocity_cells[0]))
    prior_x = start_km[0] - speed / 1000 * cfg.t0_s * np.cos(heading)
    prior_y = start_km[1] - speed / 1000 * cfg.t0_s * np.sin(heading)
    target = TargetSpec(9, "known_velocity", prior_x, prior_y, 1, speed, heading)
    tpm = TargetProbabilityMaps((target,), cfg, n_uavs=1)
    position = np.array(start_km, dtype=float)
    step = np.array(velocity_cells, dtype=float)
    offsets = np.array([(a, b) for a in range(-2, 3) for b in range(-2, 3)])
    for _ in range(steps):
        cell = np.floor(position).astype(int)
        looked = cell + offsets
        looked = looked[GRID.inside(looked)]
        tpm.apply_looks(np.array([0]), [looked], [(looked == cell).all(axis=1)], cell[None, :])
        tpm.renormalise()
        tpm.forecast()
        position += step
        for axis in range(2):  # reflect at the area's edge, as the world does
            if position[axis] < 0:
                position[axis], step[axis] = -position[axis], -step[axis]
            if position[axis] > 100:
                position[axis], step[axis] = 200 - position[axis], -step[axis]
    return tpm, position


def test_known_velocity_belief_stays_on_a_target_crossing_cell_boundaries():
    """Eq 22 with the belief's sub-cell offset kept: looks that find the target in its true
    cell every step concentrate the belief there, whichever part of the cell it is in (the map
    moves by whole cells, up to half a cell beside the target; a look that ignored that part
    ruled the belief out at the target's true cell)."""
    # each cell false-alarming with P_F, so that one look is far from decisive
    cfg = CFG.replace(delta_0_km=1.0, false_alarm_per_look=False)
    tpm, now = _track_with_exact_looks((0.3, 0.1), (40.2, 50.5), 40, cfg)
    cell = np.floor(now).astype(int)
    belief = tpm.layer_map(0, 0)
    assert belief[cell[0] - 1 : cell[0] + 2, cell[1] - 1 : cell[1] + 2].sum() > 0.9
    assert belief[cell[0], cell[1]] > 0.5


def test_known_velocity_layer_moves_without_blurring():
    t = (TargetSpec(9, "known_velocity", 30, 50, 1, speed_mps=30, heading_rad=0.0),)
    tpm = TargetProbabilityMaps(t, CFG.replace(delta_0_km=1.0), n_uavs=1)
    start = tpm.layer_map(0, 0).copy()
    for _ in range(100):  # 0.3 km per step -> 30 km east
        tpm.forecast()
    end = tpm.layer_map(0, 0)
    mean = lambda m: (m.sum(axis=1) * GRID.centres_x_km).sum() / m.sum()  # noqa: E731
    assert mean(end) - mean(start) == pytest.approx(30.0, abs=0.6)
    assert end.max() == pytest.approx(start.max(), rel=1e-5)  # same shape, not smeared


def test_looks_at_one_cell_combine_exactly_as_sequential_eq18():
    targets = (
        TargetSpec(1, "known_position", 50, 50, 1),
        TargetSpec(2, "unknown_position", 0, 0, 1),
    )
    together = TargetProbabilityMaps(targets, CFG, n_uavs=1)
    apart = TargetProbabilityMaps(targets, CFG, n_uavs=1)
    offsets = GRID.disc_offsets(CFG.detection_radius_km)
    rng = np.random.default_rng(3)
    origins = np.array([[50, 50], [51, 49], [49, 52]])
    looks = [o + offsets for o in origins]
    bits = [rng.random(len(offsets)) < 0.5 for _ in looks]
    together.apply_looks(np.zeros(3, int), looks, bits, origins)
    for look, bit, origin in zip(looks, bits, origins, strict=True):
        apart.apply_looks(np.zeros(1, int), [look], [bit], origin[None])
    assert np.allclose(together.maps, apart.maps, rtol=1e-5, atol=1e-12)
    assert np.allclose(together.totals, apart.totals, rtol=1e-6)  # maps are stored in float32
    assert together.totals == pytest.approx(
        together.maps.sum(axis=(2, 3), dtype=np.float64), rel=1e-6
    )


def test_eq18_at_the_sensor_limits():
    prior = np.array([0.0, 0.3, 1.0, 0.5])
    # P_F = 0: a detection makes any possible target certain, an impossible one stays impossible
    assert bayes_update(prior, np.ones(4, bool), 1.0, 0.0) == pytest.approx([0.0, 1.0, 1.0, 1.0])
    # P_D = 1: a miss rules the cell out, even a certain one
    assert bayes_update(prior, np.zeros(4, bool), 1.0, 0.0) == pytest.approx([0.0, 0.0, 0.0, 0.0])


def test_boxed_known_speed_forecast_matches_the_full_grid_convolution():
    targets = (TargetSpec(1, "known_speed", 12, 50, 1, speed_mps=50),)
    tpm = TargetProbabilityMaps(targets, CFG, n_uavs=2)
    reference = tpm.maps[0].astype(np.float64).copy()
    for x0, x1, y0, y1 in tpm.ring_box[0]:
        assert (x1 - x0) * (y1 - y0) < 0.7 * GRID.size  # real saving
    for _ in range(40):
        tpm.forecast()
        reference = convolve_reflect(reference, tpm.ring_kernels[0])
    for uav, (x0, x1, y0, y1) in enumerate(tpm.ring_box[0]):
        outside = np.ones(GRID.shape, bool)
        outside[x0:x1, y0:y1] = False
        assert not tpm.maps[0][uav][outside].any()  # the box holds all the mass it claims to
    assert np.allclose(tpm.maps[0], reference, atol=1e-8)  # the x = 12 edge reflects as before


def test_a_uavs_forecast_depends_on_its_own_map_alone():
    # each UAV trims its known-speed layer's negligible border over its own map: batched with a
    # UAV that found the target's border likely (detections) where this one found it empty
    # (misses), a UAV's maps are bit for bit those it has alone
    targets = (TargetSpec(1, "known_speed", 40, 50, 1, speed_mps=50),)
    both = TargetProbabilityMaps(targets, CFG, n_uavs=2)
    alone = TargetProbabilityMaps(targets, CFG, n_uavs=1)
    for step in range(10):  # (a detection multiplies a cell by ~250: float32 holds 10 steps)
        xs, ys = np.nonzero(both.maps[0, 1])  # UAV 1's support
        x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
        border = np.array([(x, y) for x in range(x0, x1) for y in range(y0, y1)
                           if x in (x0, x1 - 1) or y in (y0, y1 - 1)])  # fmt: skip
        looks = [cell[None] for cell in border]  # one look over each cell, from above it
        miss, hit = [np.zeros(1, bool)] * len(border), [np.ones(1, bool)] * len(border)
        uavs = np.repeat([0, 1], len(border))
        both.apply_looks(uavs, looks + looks, miss + hit, np.concatenate([border, border]))
        alone.apply_looks(np.zeros(len(border), int), looks, miss, border)
        for maps in (both, alone):
            maps.renormalise()
            maps.forecast()
        assert np.isfinite(both.maps).all()
        assert np.array_equal(both.maps[:, :1], alone.maps), step


def test_the_known_position_forecast_spreads_only_the_box_that_holds_belief():
    # eq 20 over the box of the cells holding belief (grown by twice the kernel's reach) gives
    # every cell, bit for bit, what the whole area's convolution gives: at the area's edge, at
    # the box's edge, and for a map of a batch whose others hold belief elsewhere
    from planner.target_probability_map import wiener_box

    tpm = TargetProbabilityMaps((TargetSpec(1, "known_position", 50, 50, 1),), CFG, n_uavs=2)
    kernel = tpm.wiener_1d
    assert len(kernel) > 1
    rng = np.random.default_rng(3)
    for corner in ((0, 0), (GRID.nx - 15, 30), (40, GRID.ny - 10), (45, 45)):
        layer = np.zeros((2, *GRID.shape), np.float32)
        x, y = corner
        layer[0, x : x + 12, y : y + 9] = rng.random((min(12, GRID.nx - x), min(9, GRID.ny - y)))
        layer[1, 60:62, 10:13] = 0.5
        whole, work = layer.copy(), np.empty_like(layer)
        ndimage.convolve1d(whole, kernel, axis=1, mode="reflect", output=work)
        ndimage.convolve1d(work, kernel, axis=2, mode="reflect", output=whole)
        tpm.maps[0] = layer
        tpm._wiener_forecast([0])
        assert np.array_equal(tpm.maps[0].view(np.uint32), whole.view(np.uint32)), corner
        x0, x1, y0, y1 = wiener_box(layer, len(kernel) // 2)
        assert (x1 - x0) * (y1 - y0) < 0.8 * GRID.size  # a real saving
    assert wiener_box(np.zeros((2, *GRID.shape), np.float32), 4) is None  # nothing to spread


def test_the_stencil_over_maps_some_of_them_equal_is_each_maps_own_stencil():
    # UAVs that heard the same looks hold the same map: the stencil runs once per distinct
    # map and copies the result; each map comes out bit for bit as stencilled alone over its
    # own box (equal maps with boxes of different sizes, one at the area's edge)
    rng = np.random.default_rng(3)
    kernel = ring_kernel(0.4)
    maps = np.zeros((7, 60, 90), dtype=np.float32)
    boxes = np.array([[0, 30, 5, 60], [3, 40, 0, 45], [0, 30, 5, 60], [0, 34, 2, 64],
                      [3, 40, 0, 45], [40, 60, 60, 90], [0, 30, 5, 60]])  # fmt: skip
    # enough cells that the stencil looks for the equal maps
    assert len(maps) * box_cells(union_box(boxes)) >= DISTINCT_MIN_CELLS
    for i, (x0, x1, y0, y1) in enumerate(boxes[[0, 1, 5]]):
        maps[[0, 1, 5][i], x0:x1, y0:y1] = rng.random((x1 - x0, y1 - y0))
    maps[[2, 3, 6]] = maps[0]  # map 3 the same as map 0 within a larger box
    maps[4] = maps[1]
    sums = maps.sum(axis=(1, 2), dtype=np.float64)
    assert len(distinct_maps(maps, sums)[0]) == 3
    alone = [m[None].copy() for m in maps]
    for m, box in zip(alone, boxes, strict=True):
        SquareStencil(m.shape, m.dtype).apply(m, kernel, tuple(box))
    # alike by their sums, and all alike (every map compared with the first)
    for alike in (sums, np.zeros(len(maps))):
        batched = maps.copy()
        stencil = SquareStencil(maps.shape, maps.dtype)
        stencil.chunk = 2  # the distinct maps in more than one batch
        stencil.apply(batched, kernel, boxes=boxes, alike=alike)
        assert np.array_equal(batched, np.concatenate(alone))
        assert np.array_equal(batched[3], batched[0]) and not np.array_equal(batched[0], batched[1])
