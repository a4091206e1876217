"""A planner of one's own, registered from outside the project's packages with a Python entry
point (group ``swarmplan.planners``), flies through ``swarmplan run`` and ``swarmplan
experiment`` like the paper's three. The planner is the example of docs/architecture.md, taken
from the page, so the page's example is the one that is tested."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
NO_VIOLATIONS = {"threat": 0, "separation": 0, "turn": 0, "range": 0}


def example_planner_code() -> str:
    """The Python block of docs/architecture.md that follows 'greedy_planner.py'."""
    page = (ROOT / "docs" / "architecture.md").read_text()
    found = re.search(r"greedy_planner\.py.*?```python\n(.*?)```", page, re.S)
    assert found, "docs/architecture.md lost its example planner"
    return found.group(1)


@pytest.fixture
def plugin_path(tmp_path: Path) -> Path:
    """A folder holding the example planner as an installed distribution would: the module and
    a dist-info whose entry_points.txt registers it as 'greedy'."""
    (tmp_path / "greedy_planner.py").write_text(example_planner_code())
    info = tmp_path / "greedy_planner-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: greedy-planner\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[swarmplan.planners]\ngreedy = greedy_planner:GreedyPlanner\n"
    )
    return tmp_path


def swarmplan(args: list[str], plugin_path: Path, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(plugin_path), str(ROOT)]))
    return subprocess.run(
        [sys.executable, "-m", "swarmplan", *args],
        cwd=cwd, env=env, capture_output=True, text=True, timeout=240,
    )  # fmt: skip


def test_a_registered_planner_flies_through_swarmplan_run(plugin_path, tmp_path):
    out = tmp_path / "run"
    done = swarmplan(
        ["run", "paper-10uav", "--algorithm", "greedy", "--steps", "40", "--out", str(out),
         "--json"], plugin_path, tmp_path,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["algorithm"] == "greedy"
    assert result["violations"] == NO_VIOLATIONS
    # it searched: every UAV moved and the swarm covered ground
    assert all(len({tuple(c) for c in u["track_km"]}) > 20 for u in result["uavs"])
    assert result["coverage"] > 0.1
    assert (out / "result.json").exists()
    # the shared building blocks kept the swarm apart and outside the threats it found
    assert result["min_separation_km"] >= 1.0


def test_a_registered_planner_runs_in_an_experiment_beside_hapf_aco(plugin_path, tmp_path):
    out = tmp_path / "experiment"
    done = swarmplan(
        ["experiment", "efficiency", "--algorithms", "greedy,hapf-aco", "--runs", "1",
         "--steps", "20", "--jobs", "1", "--quiet", "--out", str(out)], plugin_path, tmp_path,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert (out / "runs" / "paper-2uav" / "greedy").is_dir()
    assert (out / "runs" / "paper-2uav" / "hapf-aco").is_dir()


def test_an_unknown_algorithm_is_one_line_naming_the_registered_ones(plugin_path, tmp_path):
    done = swarmplan(["run", "paper-2uav", "--algorithm", "mine"], plugin_path, tmp_path)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert "unknown algorithm 'mine'" in lines[0] and "greedy" in lines[0]
    assert "swarmplan.planners" in lines[0]
