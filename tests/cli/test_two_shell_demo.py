"""The two-shell example of docs/daemon.md (``swarmplan sim --lockstep & swarmplan daemon
--lockstep``, with their default scenario and seed) flies the very mission ``swarmplan demo``
flies: ``sim`` and ``daemon`` once defaulted to seed 0 while ``run`` and ``demo`` used 1;
``swarmplan account`` joins the simulator's ground truth to the daemon's result into the very
per-target account the demo gives; and the simulator's ground-truth safety account, which the
demo merges into result.json as ``simulator_truth``, is the two-shell user's too: the simulator
prints it (``safety``) in the JSON summary it ends with."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from loopback import free_udp_port, run_swarmplan, start_swarmplan, stop

from sim_gateway.target_account import align_steps
from swarmplan.arguments import DEFAULT_SEED
from swarmplan.demo import simulator_summary

STEPS = 12

#: The run's own bookkeeping, not the mission flown; and what only the demo joins in from the
#: simulator it runs (the daemon flies MAVLink vehicles: SITL or aircraft have no ground truth)
VOLATILE = {"wall_time_s", "endpoints", "frames_received", "tlog", "target_account"}
FROM_THE_SIMULATOR = {"simulator_truth"}
#: The simulator's ground truth, written when it stops (``swarmplan sim --target-account``).
TRUTH = "target_truth.json"


def two_shells(out: Path) -> tuple[dict, dict]:
    """``swarmplan sim --lockstep`` in the background, then ``swarmplan daemon --lockstep``, both
    with their defaults but for a free port (the docs use 14550) and a short mission; then the
    simulator stopped as the docs say (Ctrl-C or ``kill``). The daemon's result and the
    simulator's summary."""
    port = free_udp_port()
    log = out.parent / "sim.log"
    sim = start_swarmplan(
        ["sim", "--lockstep", "--gcs-port", str(port), "--target-account", str(out.parent / TRUTH)],
        log,
    )
    try:
        proc = run_swarmplan(
            ["daemon", "--lockstep", "--connect", f"udpin:127.0.0.1:{port}",
             "--steps", str(STEPS), "--no-view", "--json", "--out", str(out)],
            timeout=150,
        )  # fmt: skip
    finally:
        stop(sim)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = simulator_summary(log)  # what the demo reads from its simulator
    assert summary is not None, log.read_text()[-2000:]
    return json.loads(proc.stdout), summary


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
        (a, simulator), b = shells.result(), alone.result()
    assert a["seed"] == b["seed"] == DEFAULT_SEED and a["scenario"] == b["scenario"]
    assert a["steps"] == b["steps"] == STEPS
    assert [u["track_km"] for u in a["uavs"]] == [u["track_km"] for u in b["uavs"]]
    assert a["coverage_curve"] == b["coverage_curve"] and a["engagements"] == b["engagements"]
    keys = (set(a) | set(b)) - VOLATILE - FROM_THE_SIMULATOR
    assert {k: a.get(k) for k in keys} == {k: b.get(k) for k in keys}
    # the daemon alone has no truth; `swarmplan account` joins the simulator's, as the demo does
    out = tmp_path / "shells" / "out"
    assert "target_account" not in json.loads((out / "result.json").read_text())
    joined = run_swarmplan(["account", str(out), "--truth", str(out.parent / TRUTH)], timeout=60)
    assert joined.returncode == 0, joined.stderr[-2000:]
    assert "conversion" in joined.stdout and (out / "targets.png").stat().st_size > 0
    account = json.loads((out / "result.json").read_text())["target_account"]
    assert account == b["target_account"] and account["totals"]["pursued"] is not None
    # every daemon step found its simulator step by the looks' time stamps
    result = json.loads((out / "result.json").read_text())
    truth = json.loads((out.parent / TRUTH).read_text())
    aligned = align_steps(truth, dict(result["look_times_ms"]), tolerance_ms=500.0)
    assert aligned["steps"] == list(range(STEPS + 1))
    # bad input: one line naming the problem and the fix, exit 2
    for bad in (["--truth", str(out / "result.json")], ["--truth", str(tmp_path / "none.json")]):
        proc = run_swarmplan(["account", str(out), *bad], timeout=60)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    # the ground truth of what flew: in the demo's result, and in the simulator's own summary
    assert "simulator_truth" not in a and b["simulator_truth"]["source"].startswith("simulator")
    assert simulator["safety"] == b["simulator_truth"]


def test_every_command_defaults_to_one_seed():
    from swarmplan.cli import build_parser

    parser = build_parser()
    for command in (["run", "paper-2uav"], ["demo"], ["sim"], ["daemon"]):
        assert parser.parse_args(command).seed == DEFAULT_SEED, command
