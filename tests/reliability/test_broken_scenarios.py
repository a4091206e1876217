"""Every file of the broken-scenario corpus (tests/reliability/broken_scenarios/: missing fields,
wrong types, targets outside the area, negative radii, a start inside a threat, overlapping
starts, threats covering the area, absurd sizes, garbage bytes...) makes ``swarmplan run FILE``
print one line naming the problem and exit 2: never a traceback, never a hang."""

from __future__ import annotations

from pathlib import Path

import pytest
from loopback import run_swarmplan

from swarmplan.cli import main

CORPUS = sorted((Path(__file__).parent / "broken_scenarios").glob("*.toml"))


def test_the_corpus_is_there():
    assert len(CORPUS) >= 30


@pytest.mark.timeout(60)
@pytest.mark.parametrize("path", CORPUS, ids=[p.stem for p in CORPUS])
def test_broken_scenario_is_one_clear_line_and_exit_2(path: Path, tmp_path: Path, capsys):
    status = main(["run", str(path), "--steps", "2", "--json", "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert status == 2, err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("swarmplan run: error: scenario "), err
    assert path.name in lines[0] or path.stem in lines[0]
    assert not (tmp_path / "result.json").exists()


@pytest.mark.timeout(60)
def test_broken_scenarios_through_the_real_command_line(tmp_path: Path):
    for name in ("garbage_bytes", "grid_huge", "start_inside_threat"):
        proc = run_swarmplan(
            ["run", str(CORPUS[0].parent / f"{name}.toml"), "--out", str(tmp_path)], timeout=60
        )
        assert proc.returncode == 2
        assert "Traceback" not in proc.stderr
        assert proc.stderr.strip().splitlines()[-1].startswith("swarmplan run: error: scenario")


@pytest.mark.timeout(60)
def test_a_threat_that_leaves_no_room_for_the_starts_is_named_with_the_file(tmp_path: Path):
    """Issue 31: a copy of paper-10uav (still named so) with a threat of radius 500 km said
    "scenario 'paper-10uav': cannot place 10 UAVs clear of the threats", naming neither the
    threat nor the file. Now the planner and the simulator say both, and the fix."""
    path = CORPUS[0].parent / "threat_radius_500km.toml"
    for command in (
        ["run", str(path), "--out", str(tmp_path)],
        ["sim", "--scenario", str(path), "--duration-s", "1", "--quiet"],
    ):
        proc = run_swarmplan(command, timeout=60)
        assert proc.returncode == 2, (command, proc.stderr)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
        assert str(path) in lines[0], lines[0]
        assert "threats[0] (centre (30, 65) km, radius_km 500)" in lines[0], lines[0]
        assert "make radius_km smaller" in lines[0] and "[[uavs.start]]" in lines[0]
