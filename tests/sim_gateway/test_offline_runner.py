import numpy as np
import pytest

from planner.grid import Grid
from planner.scenario import load_scenario
from sim_gateway.offline_runner import run_offline
from sim_gateway.world import World


@pytest.mark.parametrize(
    ("name", "seeds", "steps"), [("paper-2uav", [1, 2], 250), ("paper-10uav", [1, 2, 3, 4], 250)]
)
def test_paper_scenarios_fly_without_any_violation(name, seeds, steps):
    scenario = load_scenario(name)
    for seed in seeds:
        result = run_offline(scenario, seed, steps)
        assert result["violations"] == {"threat": 0, "separation": 0, "turn": 0, "range": 0}, (
            name,
            seed,
        )
        assert len(result["coverage_curve"]) == steps + 1
        assert np.all(np.diff(result["coverage_curve"]) >= 0)
        assert result["min_separation_km"] >= scenario.config.min_separation_km
        if np.isfinite(scenario.config.max_range_km):
            assert max(u["distance_km"] for u in result["uavs"]) <= scenario.config.max_range_km
        modes = result["decision_modes"]  # every UAV's mode at every step, counted once
        assert sum(modes.values()) == steps * scenario.uav_count, modes
        assert modes["heuristic"] > sum(modes.values()) / 2, modes
        if scenario.config.home_by_end:  # back home at the end: returned, then held
            assert modes["return"] > 0 and modes["hold"] > 0, modes


def test_a_recorder_from_an_older_checkpoint_counts_modes_from_the_resume_on():
    """A daemon checkpoint pickled before decision modes were counted still resumes."""
    import pickle

    from planner.metrics import MissionRecorder

    scenario = load_scenario("paper-2uav")
    old = MissionRecorder(scenario, scenario.starts_for_seed(1))
    del old.mode_steps  # as the recorder was pickled before the count existed
    resumed = pickle.loads(pickle.dumps(old))
    resumed.record_modes(np.array([5, 1]))
    modes = resumed.result(1, "hapf-aco", 0.0)["decision_modes"]
    assert modes["heuristic"] == 1 and modes["return"] == 1 and sum(modes.values()) == 2


def test_same_seed_same_result_and_other_seed_differs():
    s = load_scenario("paper-10uav")
    a, b, c = run_offline(s, 7, 60), run_offline(s, 7, 60), run_offline(s, 8, 60)
    strip = lambda r: {k: v for k, v in r.items() if k != "wall_time_s"}  # noqa: E731
    assert strip(a) == strip(b)
    assert strip(a) != strip(c)


@pytest.mark.parametrize("per_look", [True, False])
def test_sensor_reports_true_targets_more_often_than_false_alarms(per_look):
    s = load_scenario("paper-2uav").with_config(false_alarm_per_look=per_look)
    world = World(s, 3)
    grid = Grid()
    target = world.positions[12]  # a stationary target
    hits, alarms, alarmed_looks, looks = 0, 0, 0, 2000
    for _ in range(looks):
        report = world.sense(grid.centre_km(grid.cell_of(target[None])))[0]
        here = (report.cells == grid.cell_of(target[None])[0]).all(axis=1)
        hits += int(report.detected[here].sum())
        alarms += int(report.detected[~here].sum())
        alarmed_looks += int(report.detected[~here].any())
    assert hits / looks > 0.8
    if per_look:  # P_F is a look's: about one look in ten reports a cell with no target
        assert alarmed_looks / looks == pytest.approx(s.config.p_false, abs=0.02)
    else:  # each of the other 28 cells false-alarms with P_F
        assert alarms / (looks * 28) == pytest.approx(s.config.p_false, abs=0.01)


def test_engagement_needs_a_target_within_the_engage_radius():
    world = World(load_scenario("paper-2uav"), 1)
    far = world.engage(np.array([0.5, 99.5]))
    assert not far.success
    near = world.engage(world.positions[0] + [0.3, 0.3], step=4)
    assert near.success and near.target_id == 1 and near.value == 3
    assert not world.alive[0] and not world.engage(world.positions[0]).success
