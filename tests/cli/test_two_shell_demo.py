"""The two-shell example of docs/daemon.md (``swarmplan sim --lockstep & swarmplan daemon
--lockstep``, with their default scenario and seed) flies the very mission ``swarmplan demo``
flies: ``sim`` and ``daemon`` once defaulted to seed 0 while ``run`` and ``demo`` used 1."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from loopback import free_udp_port, run_swarmplan, start_swarmplan, stop

from swarmplan.arguments import DEFAULT_SEED

STEPS = 12

#: The run's own bookkeeping (and what only the demo joins in), not the mission flown.
VOLATILE = {"wall_time_s", "endpoints", "frames_received", "tlog", "target_account"}


def two_shells(out: Path) -> dict:
    """``swarmplan sim --lockstep`` in the background, then ``swarmplan daemon --lockstep``, both
    with their defaults but for a free port (the docs use 14550) and a short mission."""
    port = free_udp_port()
    sim = start_swarmplan(["sim", "--lockstep", "--gcs-port", str(port)], out.parent / "sim.log")
    try:
        proc = run_swarmplan(
            ["daemon", "--lockstep", "--connect", f"udpin:127.0.0.1:{port}",
             "--steps", str(STEPS), "--no-view", "--json", "--out", str(out)],
            timeout=150,
        )  # fmt: skip
    finally:
        stop(sim)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout)


def demo(out: Path) -> dict:
    proc = run_swarmplan(
        ["demo", "--steps", str(STEPS), "--no-view", "--json", "--out", str(out)], timeout=150
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout)


@pytest.mark.timeout(200)
def test_the_docs_two_shell_example_reproduces_the_demo(tmp_path):
    (tmp_path / "shells").mkdir()
    with ThreadPoolExecutor(2) as pool:  # both lockstep: the load cannot change either result
        shells = pool.submit(two_shells, tmp_path / "shells" / "out")
        alone = pool.submit(demo, tmp_path / "demo")
        a, b = shells.result(), alone.result()
    assert a["seed"] == b["seed"] == DEFAULT_SEED and a["scenario"] == b["scenario"]
    assert a["steps"] == b["steps"] == STEPS
    assert [u["track_km"] for u in a["uavs"]] == [u["track_km"] for u in b["uavs"]]
    assert a["coverage_curve"] == b["coverage_curve"] and a["engagements"] == b["engagements"]
    keys = (set(a) | set(b)) - VOLATILE
    assert {k: a.get(k) for k in keys} == {k: b.get(k) for k in keys}


def test_every_command_defaults_to_one_seed():
    from swarmplan.cli import build_parser

    parser = build_parser()
    for command in (["run", "paper-2uav"], ["demo"], ["sim"], ["daemon"]):
        assert parser.parse_args(command).seed == DEFAULT_SEED, command
