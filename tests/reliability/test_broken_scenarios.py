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
