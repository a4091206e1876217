"""The mission view without a browser: belief snapshots, the replay file (round trip, a file cut
short, bad folders), the feed's hand-over that never makes the decision loop wait, the server's
port errors and ``swarmplan view``'s bad input."""

from __future__ import annotations

import gzip
import socket
import threading

import numpy as np
import pytest
from loopback import run_swarmplan

from mission_view.belief_layers import layer_index, layer_shape, quantise
from mission_view.feed import ViewFeed
from mission_view.mission_store import MissionStore
from mission_view.replay_file import ReplayWriter, load_replay, replay_path
from mission_view.server import ViewServer
from mission_view.sources import OfflineViews
from mission_view.view_model import StepView
from mission_view.view_session import ViewSession
from planner.belief_snapshot import belief_snapshot
from planner.errors import UserError
from planner.hapf_aco import HapfAcoPlanner
from planner.scenario import load_scenario
from sim_gateway.offline_runner import run_offline

STEPS = 12


@pytest.fixture(scope="module")
def scenario():
    return load_scenario("paper-2uav")


@pytest.fixture(scope="module")
def recorded(scenario, tmp_path_factory):
    """An offline run recorded as ``swarmplan run`` does, with the quantised layers of every
    step kept for comparison."""
    out = tmp_path_factory.mktemp("run")
    session = ViewSession(
        scenario, seed=3, steps=STEPS, uav_count=scenario.uav_count, source="offline",
        truth=True, out_dir=out, live=False,
    )  # fmt: skip
    views = OfflineViews(scenario)
    expected = {}

    def observe(record):
        session.post(views.view(record), record.planner)
        snapshot = belief_snapshot(record.planner, record.step)
        expected[record.step] = quantise(snapshot, scenario.config)

    result = run_offline(scenario, 3, STEPS, observer=observe)
    session.close()
    return out, result, expected


def test_snapshot_is_a_read_only_copy_of_the_planner_beliefs(scenario):
    planner = HapfAcoPlanner(scenario, scenario.starts_for_seed(1), 1)
    snap = belief_snapshot(planner, 0)
    assert not snap.tpm_maps.flags.writeable and not snap.pheromone.flags.writeable
    with pytest.raises(ValueError):
        snap.coverage[0, 0, 0] = True
    np.testing.assert_allclose(snap.existence(1), planner.beliefs.tpm.existence_map(1))
    planner.pheromone.tau[0, 0, 0] = -1.0  # the planner goes on: the snapshot does not change
    assert snap.pheromone[0, 0, 0] != -1.0
    again = belief_snapshot(planner, 1, reuse=snap)  # into the old buffers, no new arrays
    assert again.pheromone is snap.pheromone and again.pheromone[0, 0, 0] == -1.0


def test_replay_round_trip_of_an_offline_run(recorded, scenario):
    out, result, expected = recorded
    store = load_replay(out)
    assert store.ended and store.step_count == STEPS + 1
    steps = store.steps_from(0)
    assert [s["step"] for s in steps] == list(range(STEPS + 1))
    # offline, every step's beliefs are recorded (nothing waits for the run)
    assert [store.layer(k, 0)[0] for k in range(STEPS + 1)] == list(range(STEPS + 1))
    for k in (0, STEPS // 2, STEPS - 1):  # the layers read back are the ones written
        found, layer = store.layer(k, layer_index("tpm", 1, 2))
        assert found == k
        np.testing.assert_array_equal(layer, expected[k][layer_index("tpm", 1, 2)])
    assert layer.shape == layer_shape(scenario.config)
    # the vehicles are where the result says they flew; the truth is there, marked per step
    for k in (0, STEPS):
        for i, uav in enumerate(result["uavs"]):
            v = steps[k]["vehicles"][i]
            assert [v["x_km"], v["y_km"]] == pytest.approx(uav["track_km"][k], abs=1e-3)
        assert len(steps[k]["truth"]) == len(scenario.targets)
    engaged = [e for s in steps for e in s["events"] if e["kind"] == "engagement"]
    assert len(engaged) == result["engaged_count"]


def test_a_replay_cut_short_reads_to_its_last_whole_line(recorded, tmp_path):
    out, _, _ = recorded
    raw = gzip.decompress(replay_path(out).read_bytes())
    cut = tmp_path / "cut"
    cut.mkdir()
    with open(replay_path(cut), "wb") as f:  # a gzip stream stopped mid-way, as after kill -9
        f.write(gzip.compress(raw)[: len(gzip.compress(raw)) * 2 // 3])
    store = load_replay(cut)
    assert 0 < store.step_count < STEPS + 1


def test_bad_replay_folders_are_one_clear_error(tmp_path):
    with pytest.raises(UserError, match="not a folder"):
        load_replay(tmp_path / "missing")
    with pytest.raises(UserError, match="has no replay.jsonl.gz"):
        load_replay(tmp_path)
    replay_path(tmp_path).write_bytes(b"not gzip at all")
    with pytest.raises(UserError, match="damaged"):
        load_replay(tmp_path)
    for args in (["view", str(tmp_path)], ["view", str(tmp_path / "missing")]):
        done = run_swarmplan(args, timeout=60)
        assert done.returncode == 2, args
        assert done.stderr.strip().splitlines() == [done.stderr.strip()], done.stderr
        assert done.stderr.startswith("swarmplan view: error: ")
    done = run_swarmplan(["view", str(tmp_path), "--port", "70000"], timeout=60)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "not a port number" in done.stderr.strip().splitlines()[-1]


class _StuckWriter(ReplayWriter):
    """A replay writer whose beliefs wait until released: a view thread that fell behind."""

    def __init__(self, path, layout):
        super().__init__(path, layout)
        self.release = threading.Event()
        self.stuck = threading.Event()
        self.beliefs_written = []

    def write_beliefs(self, step, layers):
        self.stuck.set()
        self.release.wait(60)
        self.beliefs_written.append(step)
        super().write_beliefs(step, layers)


def test_a_live_feed_never_makes_the_loop_wait_and_keeps_every_step(scenario, tmp_path):
    """With the view's thread stuck, posting goes on: every step view is kept, beliefs of the
    steps in between are dropped, and the newest ones are recorded once the thread is free."""
    store = MissionStore({"type": "mission", "uav_count": 2})
    writer = _StuckWriter(tmp_path / "replay.jsonl.gz", store.layout)
    feed = ViewFeed(store, scenario.config, writer, drop_beliefs=True)
    planner = HapfAcoPlanner(scenario, scenario.starts_for_seed(1), 1)
    views = OfflineViews(scenario)
    record = []
    run_offline(scenario, 1, 8, observer=record.append)
    feed.post(views.view(record[0]), planner)
    assert writer.stuck.wait(30)
    for r in record[1:]:  # 8 posts while the thread is stuck on the first beliefs: none may block
        feed.post(views.view(r), planner)
    assert feed.dropped_beliefs == len(record) - 2  # all but the first and the newest
    writer.release.set()
    feed.close()
    assert store.step_count == len(record)
    assert writer.beliefs_written[0] == 0 and writer.beliefs_written[-1] == record[-1].step
    assert len(writer.beliefs_written) == len(record) - feed.dropped_beliefs


def test_a_port_in_use_is_one_clear_error():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        server = ViewServer(MissionStore({"type": "mission", "uav_count": 1}), "127.0.0.1", port)
        with pytest.raises(UserError, match=f"127.0.0.1:{port}.*--view-port"):
            server.start()


def test_a_resumed_daemon_appends_to_the_replay(tmp_path):
    """The first daemon's part, then the resumed one's (from a step the first had recorded):
    one replay, each step once, the later part's layers read from its own key line."""
    rng = np.random.default_rng(5)
    layers = {k: rng.integers(0, 256, size=(3, 4, 4), dtype=np.uint8) for k in range(9)}
    layout = {"type": "mission", "uav_count": 1, "steps": 8}
    for part, (steps, append) in enumerate(((range(0, 6), False), (range(4, 9), True))):
        writer = ReplayWriter(replay_path(tmp_path), layout, append=append)
        for k in steps:
            writer.write_steps([{"step": k, "part": part, "vehicles": [], "events": []}])
            writer.write_beliefs(k, layers[k] if part else layers[k] // 2)
        writer.close(ended=part == 1)
    store = load_replay(tmp_path)
    steps = store.steps_from(0)
    assert [s["step"] for s in steps] == list(range(9))
    assert [s["part"] for s in steps] == [0, 0, 0, 0, 1, 1, 1, 1, 1]
    for k in range(9):
        found, layer = store.layer(k, 2)
        expected = layers[k] if k >= 4 else layers[k] // 2
        assert found == k and np.array_equal(layer, expected[2]), k


def test_swarmplan_view_on_a_port_in_use_names_its_own_port_option(recorded):
    """``swarmplan view --port BUSY`` is one line naming ``--port``, not the daemon's options."""
    out, _, _ = recorded
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        done = run_swarmplan(["view", str(out), "--port", str(port)], timeout=60)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    line = done.stderr.strip()
    assert line.splitlines() == [line] and f"127.0.0.1:{port}" in line
    assert "--port" in line and "--view-port" not in line and "--no-view" not in line, line


def test_replay_keeps_each_phase_line_with_its_step_and_marks_a_cut(tmp_path):
    """Phase lines are read back with the step they began at (the page shows the one that held
    at the step viewed); a file without its end line is marked cut short."""
    layout = {"type": "mission", "uav_count": 1, "steps": 8}
    store = MissionStore(layout)
    feed = ViewFeed(store, load_scenario("paper-2uav").config,
                    ReplayWriter(replay_path(tmp_path), layout), drop_beliefs=True)  # fmt: skip
    feed.phase("launch (take off): airborne, GUIDED")
    for k in range(4):
        if k == 0:
            feed.phase("search: the planner flies the swarm", 0)
        feed.post(StepView(k, []))
    feed.phase("return: RTL sent to vehicles 1")
    feed.close()
    said = [(p["step"], p["text"].split(":")[0]) for p in load_replay(tmp_path).phases]
    assert said == [(-1, "launch (take off)"), (0, "search"), (3, "return")]
    assert load_replay(tmp_path).layout["cut_short"] is False
    # the same mission cut short: no end line
    with gzip.open(replay_path(tmp_path), "rt") as lines:
        kept = [line for line in lines if '"type":"end"' not in line]
    with gzip.open(replay_path(tmp_path), "wt") as lines:
        lines.writelines(kept)
    assert load_replay(tmp_path).layout["cut_short"] is True
