"""The per-target account (sim_gateway/target_account.py + planner/pursuit_log.py): consistent
with the world's truth, totals from the rows, and read-only (the flight is the same without it)."""

import numpy as np

from planner.engagement import EngagementOutcome
from planner.hapf_aco import HapfAcoPlanner
from planner.pursuit_log import PursuitLog
from planner.scenario import load_scenario
from sim_gateway.offline_runner import run_offline
from sim_gateway.target_account import TargetAccount, account_of
from sim_gateway.world import World


def strip(result: dict) -> dict:
    return {k: v for k, v in result.items() if k not in ("wall_time_s", "target_account")}


def test_account_agrees_with_the_engagements_and_its_totals_with_its_rows():
    scenario = load_scenario("paper-10uav")
    result = run_offline(scenario, 4, 90)
    account = result["target_account"]
    rows = account["targets"]
    assert [r["id"] for r in rows] == [t.id for t in scenario.targets]
    assert {r["kind"] for r in rows} == {t.kind for t in scenario.targets}
    by_id = {r["id"]: r for r in rows}
    engaged = [r for r in rows if r["outcome"] == "engaged"]
    assert len(engaged) == result["engaged_count"] > 0
    for e in result["engagements"]:
        row = by_id[e["target_id"]]
        assert (row["engaged_step"], row["engaged_uav"]) == (e["step"], e["uav"])
        # a target engaged was in a footprint, sighted before and detected by the sensor
        assert row["steps_in_footprint"] > 0 and row["first_sighting"] <= e["step"]
        assert row["detections"] > 0 and row["first_detection"] <= e["step"]
        # ... and the planner believed in it enough to ask: confirmed, pursued before
        assert row["belief_peak"] >= scenario.config.confirm_threshold
        assert row["pursued_step"] is not None and row["pursued_step"] <= e["step"]
    for row in rows:
        assert (row["outcome"] == "never seen") == (row["steps_in_footprint"] == 0)
        assert row["seen"] == (row["steps_in_footprint"] >= account["seen_min_steps"])
        assert row["detections"] <= row["steps_in_footprint"]
        if row["confirmed_step"] is not None:
            assert row["pursued_step"] <= row["confirmed_step"]
    totals = account["totals"]
    assert totals["targets"] == len(rows)
    for stage, test in [
        ("in_footprint", lambda r: r["steps_in_footprint"] > 0),
        ("seen", lambda r: r["seen"]),
        ("pursued", lambda r: r["pursued_step"] is not None),
        ("confirmed", lambda r: r["confirmed_step"] is not None),
        ("engaged", lambda r: r["outcome"] == "engaged"),
        ("missed", lambda r: r["outcome"] == "missed"),
        ("never_seen", lambda r: r["outcome"] == "never seen"),
    ]:
        assert totals[stage] == sum(map(test, rows)), stage
        assert totals[stage] == sum(k[stage] for k in account["by_kind"].values()), stage
    assert totals["engaged_value"] == result["engaged_value"]
    assert totals["conversion"] == round(totals["engaged"] / totals["seen"], 4)
    assert totals["targets"] >= totals["in_footprint"] >= totals["seen"]


def test_footprint_steps_follow_the_true_distance_to_the_uavs():
    """Counted by hand from the world's truth: a UAV parked on a stationary target sees it at
    every step; one 20 km away never; the sensor's detections of it are counted too."""
    scenario = load_scenario("paper-2uav")
    world = World(scenario, 5)
    account = TargetAccount(world)
    target = next(i for i, t in enumerate(scenario.targets) if t.kind == "unknown_position")
    here = world.positions[target]
    far = np.clip(here + 20.0, 0, 99.0)
    for step in range(6):
        uavs = np.array([here, far])
        looks = world.sense(uavs)
        # the second UAV is not airborne at odd steps: its footprint does not count then
        account.observe(step, uavs, np.array([True, step % 2 == 0]), looks)
        world.step()
    truth = account.truth()
    rows = account_of(truth)["targets"]
    row = rows[target]
    assert row["steps_in_footprint"] == 6 and row["first_sighting"] == 0
    assert 1 <= row["detections"] <= 6
    # a simulator runs on after the mission: the account is cut at the mission's last step
    assert account_of(truth, last_step=2)["targets"][target]["steps_in_footprint"] == 3
    # every target: counted at least at the steps some airborne UAV was well within R of it,
    # at most at those it was within R plus the cells' rounding (the sensor works on cells)
    radius, slack = scenario.config.detection_radius_km, np.sqrt(2.0) * scenario.config.cell_km
    positions = np.asarray(truth["positions_km"])  # (steps, targets, 2)
    uav_sets = [[here, far] if s % 2 == 0 else [here] for s in truth["steps"]]
    nearest = np.array([
        np.min([np.hypot(*(positions[s] - u).T) for u in uavs], axis=0)
        for s, uavs in enumerate(uav_sets)
    ])  # fmt: skip
    for k, other in enumerate(rows):
        low = int(np.sum(nearest[:, k] <= radius - slack))
        high = int(np.sum(nearest[:, k] <= radius + slack))
        assert low <= other["steps_in_footprint"] <= high, other["id"]
    outcome = world.engage(here, 6)
    assert outcome.success and outcome.target_id == scenario.targets[target].id
    account.record_engagement(6, 0, outcome)
    account.record_engagement(6, 1, EngagementOutcome(False))
    joined = account_of(account.truth())
    assert joined["targets"][target]["outcome"] == "engaged"
    assert joined["targets"][target]["engaged_uav"] == 0
    assert joined["totals"]["pursued"] is None  # no planner facts: not claimed


def test_the_account_only_reads_the_planner_never_feeds_it():
    """The same mission with and without the account (truth bookkeeping + the planner's log):
    identical decisions, engagements and metrics, so no truth reached the planner."""
    scenario = load_scenario("paper-2uav")
    for algorithm in ("hapf-aco", "pso", "acoapf"):
        with_account = run_offline(scenario, 2, 40, algorithm)
        without = run_offline(scenario, 2, 40, algorithm, account=False)
        assert "target_account" not in without
        assert strip(with_account) == strip(without), algorithm


def test_pursuit_log_records_the_planners_own_belief_and_tracks():
    scenario = load_scenario("paper-2uav")
    planner = HapfAcoPlanner(scenario, scenario.starts_for_seed(1), 1)
    log = PursuitLog(floor=0.0).attach(planner)
    world = World(scenario, 1)
    cells = planner.beliefs.cells.copy()
    headings = planner.beliefs.headings.copy()
    for _ in range(3):
        decision = planner.step(cells, headings, world.sense(planner.grid.centre_km(cells)))
        cells, headings = decision.next_cells, decision.next_headings
        world.step()
    facts = log.facts()
    steps = {b[0] for b in facts["beliefs"]}
    assert steps == {0, 1, 2}
    # floor 0: every footprint cell of each UAV is logged at each step, one entry per cell
    per_step = [sum(b[0] == s for b in facts["beliefs"]) for s in range(3)]
    assert min(per_step) >= len(planner.beliefs.footprint)
    assert all(0.0 <= b[3] <= 1.0 for b in facts["beliefs"])


def test_pursuit_log_skips_only_cells_whose_belief_is_under_its_floor():
    """The log prunes footprint cells by a union bound before computing their belief; what it
    keeps is exactly what computing every footprint and track cell would keep."""
    scenario = load_scenario("paper-10uav")
    planner = HapfAcoPlanner(scenario, scenario.starts_for_seed(3), 3)
    log = PursuitLog().attach(planner)
    every: list[list[float]] = []

    def exhaustive(beliefs, decision):
        flying = np.flatnonzero(~np.asarray(beliefs.done, dtype=bool))
        cells = beliefs.cells[flying][:, None, :] + beliefs.footprint[None]
        cells = np.concatenate([cells, beliefs.track[flying][:, None, :]], axis=1)
        rows = np.repeat(flying, cells.shape[1])
        cells = cells.reshape(-1, 2)
        inside = beliefs.grid.inside(cells)
        rows, cells = rows[inside], cells[inside]
        p = beliefs.engage_probability(rows, cells)
        best: dict[tuple[int, int], float] = {}
        for (x, y), v in zip(cells.tolist(), p.tolist(), strict=True):
            if v >= log.floor:
                best[(x, y)] = max(v, best.get((x, y), 0.0))
        every.extend([int(beliefs.k), x, y, round(v, 4)] for (x, y), v in sorted(best.items()))

    planner.beliefs.observers.append(exhaustive)
    world = World(scenario, 3)
    cells, headings = planner.beliefs.cells.copy(), planner.beliefs.headings.copy()
    for _ in range(25):
        decision = planner.step(cells, headings, world.sense(planner.grid.centre_km(cells)))
        cells, headings = decision.next_cells, decision.next_headings
        world.step()
    logged = sorted(tuple(b) for b in log.facts()["beliefs"])
    assert len(logged) > 0
    assert logged == sorted(tuple(b) for b in every)
