"""A planner node restarted mid-mission (``swarmplan node --checkpoint F --resume``): the
simulator with its radio (``swarmplan sim --per-vehicle-ports``) and one ``swarmplan node``
process per UAV on loopback UDP with free ports, two UAVs of paper-10uav at 10x. Node 1 is
SIGKILLed after a few steps (a companion computer losing power) and started again with
``--resume``: it takes its plane back, rejoins the swarm at the swarm's step, flies every step to
the end and brings the plane home, with zero violations (the simulator's truth); its part says
that it resumed. And the lines a node gives for a checkpoint it cannot resume from."""

from __future__ import annotations

import json
import re
import signal
import time
from pathlib import Path

import loopback
import pytest

from planner.scenario import load_scenario

STEPS = 24
KILL_AFTER_STEP = 2
SPEEDUP = 20


def _scenario(tmp_path: Path, uavs: int = 2) -> Path:
    """paper-10uav with fewer UAVs (a few processes on the CI's two cores)."""
    text = (Path(loopback.REPO) / "planner/scenarios/paper-10uav.toml").read_text()
    path = tmp_path / f"paper-{uavs}uav-onboard.toml"
    path.write_text(text.replace("count = 10", f"count = {uavs}"))
    assert load_scenario(path).uav_count == uavs
    return path


def _node_args(scenario: Path, base: int, uav: int, out: Path, *extra: str) -> list[str]:
    return ["node", str(scenario), "--connect", f"udpin:127.0.0.1:{base + uav}", "--uav",
            str(uav), "--seed", "2", "--steps", str(STEPS), "--time-scale", str(SPEEDUP),
            "--no-leg-timing", "--out", str(out), *extra]  # fmt: skip


def _wait_for(log: Path, pattern: str, proc, timeout_s: float) -> re.Match:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        found = re.search(pattern, log.read_text(errors="replace") if log.exists() else "")
        if found:
            return found
        assert proc.poll() is None, log.read_text()[-3000:]
        time.sleep(0.1)
    raise AssertionError(f"{pattern!r} never came: {log.read_text()[-3000:]}")


def _sim_truth(sim_log: Path) -> dict:
    lines = [x for x in sim_log.read_text().splitlines() if x.startswith("{")]
    return json.loads(lines[-1])["safety"]


@pytest.mark.timeout(120)
def test_a_node_killed_mid_mission_resumes_rejoins_and_brings_its_plane_home(tmp_path):
    scenario = _scenario(tmp_path)
    base = loopback.free_port_block(2)
    duration = STEPS * load_scenario(scenario).config.step_s + 600
    sim = loopback.start_swarmplan(
        ["sim", "--scenario", str(scenario), "--seed", "2", "--speedup", str(SPEEDUP),
         "--per-vehicle-ports", str(base), "--radio-loss", "0", "--radio-range-km", "60",
         "--duration-s", str(duration), "--quiet"], tmp_path / "sim.log")  # fmt: skip
    outs = [tmp_path / f"node-{i}" for i in range(2)]
    checkpoint = tmp_path / "node-1.ckpt"
    procs = []
    try:
        for i, out in enumerate(outs):
            out.mkdir()
            extra = ["--checkpoint", str(checkpoint)] if i == 1 else []
            procs.append(loopback.start_swarmplan(
                _node_args(scenario, base, i, out, *extra), out / "node.log"))  # fmt: skip
        log1 = outs[1] / "node.log"
        _wait_for(log1, rf"node 1: step\s+{KILL_AFTER_STEP}/", procs[1], 60)
        procs[1].send_signal(signal.SIGKILL)  # no RTL, no result: the computer lost power
        procs[1].wait(5)
        assert not (outs[1] / "result.json").exists()
        resumed = loopback.start_swarmplan(
            _node_args(scenario, base, 1, outs[1], "--checkpoint", str(checkpoint), "--resume"),
            log1)  # fmt: skip
        procs.append(resumed)
        for proc in (procs[0], resumed):
            proc.wait(60)
        loopback.stop(sim)
    finally:
        for proc in [*procs, sim]:
            loopback.stop(proc)
    assert procs[0].returncode == 0 and resumed.returncode == 0, log1.read_text()[-3000:]
    text = log1.read_text()
    rejoined = re.search(r"rejoined the swarm at step (\d+)", text)
    assert "resuming from the checkpoint of step" in text and rejoined, text[-3000:]
    assert int(rejoined.group(1)) > KILL_AFTER_STEP
    assert re.search(rf"node 1: step\s+{STEPS}/{STEPS}", text)  # every step, to the end
    part = json.loads((outs[1] / "result.json").read_text())
    assert part["ended"] == "completed" and part["resumed_from_step"] >= KILL_AFTER_STEP - 1
    assert part["returned_count"] == 1 and set(part["violations"].values()) == {0}
    assert part["link"]["reports_heard"] > 0
    other = json.loads((outs[0] / "result.json").read_text())
    assert other["ended"] == "completed" and other["returned_count"] == 1
    # the swarm is one again: at the last step the resumed node heard the other in time, and
    # so did the other, if it did before the kill (two nodes launched a look apart number their
    # steps one apart for the whole mission: the one ahead never hears the other in time)
    assert part["link"]["neighbours_heard"][-1] == 1, part["link"]
    if other["link"]["neighbours_heard"][1] == 1:
        assert other["link"]["neighbours_heard"][-1] == 1, other["link"]
    truth = _sim_truth(tmp_path / "sim.log")
    assert truth["threat_entries"] == 0 and truth["separation_breaches"] == 0


# ---------------------------------------------------------------------- bad input: one line


def _write_checkpoint(path: Path, scenario: str, seed: int, uav: int | None) -> Path:
    """The checkpoint at the start of a mission of ``STEPS`` steps: written by the node of
    ``uav`` (None: by the daemon of the whole fleet), as they write it."""
    from mavlink_bridge.mission.daemon import DaemonOptions, MissionDaemon
    from mavlink_bridge.mission.onboard_planner import OnboardPlanner
    from mavlink_bridge.results.checkpoint import CheckpointWriter

    plan = load_scenario(scenario)
    role = "daemon" if uav is None else f"node {uav}"
    fleet = None if uav is None else (uav,)
    options = DaemonOptions(
        connect=["udpin:127.0.0.1:9"], seed=seed, steps=STEPS, fleet=fleet, checkpoint_role=role
    )
    daemon = MissionDaemon(plan, options)
    if uav is not None:
        daemon.planner_factory = lambda link: lambda p, s, k: OnboardPlanner(
            p, s, k, uav=uav, link=link, period_wall_s=lambda: 1.0)  # fmt: skip
    template = daemon.checkpoint_template()
    counters = daemon.account
    loop = {k: v for k, v in template.items() if k != "daemon"}
    CheckpointWriter(path, daemon.fingerprint, role=role).save(0, counters, loop, 0.0)
    return path


def _resume_node(tmp_path: Path, checkpoint: Path, uav: int = 1, seed: int = 2):
    args = ["node", "paper-10uav", "--connect", f"udpin:127.0.0.1:{loopback.free_udp_port()}",
            "--uav", str(uav), "--seed", str(seed), "--steps", str(STEPS), "--checkpoint",
            str(checkpoint), "--resume", "--out", str(tmp_path / "out")]  # fmt: skip
    return loopback.run_swarmplan(args, timeout=60)


def _one_line_exit_2(proc, *words: str) -> None:
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    for word in words:
        assert word in proc.stderr, proc.stderr


def test_a_node_resumes_only_from_a_checkpoint_that_is_there(tmp_path):
    proc = _resume_node(tmp_path, tmp_path / "none.ckpt")
    _one_line_exit_2(proc, "no checkpoint at", "run without --resume")


@pytest.mark.parametrize(
    ("writer", "seed", "words"),
    [
        (0, 2, ("written by the node of UAV 0, not by the node of UAV 1",)),
        (None, 2, ("written by the daemon, not by the node of UAV 1",)),
        (1, 3, ("belongs to another mission", "without --resume")),
    ],
    ids=["another-uav", "a-daemons", "another-seed"],
)
def test_a_node_refuses_a_checkpoint_of_another_uav_daemon_or_mission(tmp_path, writer, seed,
                                                                      words):  # fmt: skip
    checkpoint = _write_checkpoint(tmp_path / "x.ckpt", "paper-10uav", seed, writer)
    _one_line_exit_2(_resume_node(tmp_path, checkpoint), *words)


def test_a_daemon_refuses_a_nodes_checkpoint(tmp_path):
    checkpoint = _write_checkpoint(tmp_path / "x.ckpt", "paper-10uav", 2, 1)
    port = loopback.free_udp_port()
    args = ["daemon", "--scenario", "paper-10uav", "--seed", "2", "--steps", str(STEPS),
            "--connect", f"udpin:127.0.0.1:{port}", "--checkpoint", str(checkpoint), "--resume",
            "--no-view", "--out", str(tmp_path / "out")]  # fmt: skip
    proc = loopback.run_swarmplan(args, timeout=60)
    _one_line_exit_2(proc, "written by the node of UAV 1, not by the daemon")


def test_a_node_resumed_with_another_scenario_is_refused(tmp_path):
    checkpoint = _write_checkpoint(tmp_path / "x.ckpt", str(_scenario(tmp_path)), 2, 1)
    _one_line_exit_2(_resume_node(tmp_path, checkpoint), "belongs to another mission")


def test_every_range_check_names_a_part_of_a_nodes_state(tmp_path):
    """The checks of a checkpoint's ranges reach a node's state as they reach the daemon's (a
    path that names nothing would be skipped in silence)."""
    from mavlink_bridge.results.checkpoint import read_checkpoint
    from mavlink_bridge.results.checkpoint_layout import MISSING, RANGES, range_part

    loop = read_checkpoint(_write_checkpoint(tmp_path / "x.ckpt", "paper-10uav", 2, 1)).loop
    assert type(loop["planner"]).__name__ == "OnboardPlanner"
    for path in RANGES:
        part = range_part(loop, path)
        assert part is not None and part is not MISSING, f"RANGES names {path}: nothing there"


@pytest.mark.parametrize(
    ("heard", "step", "how"),
    [
        (10, 10, "heard of its neighbours"),
        (-1, 9, "by the mission's clock"),  # nobody heard
        (18, 18, "heard of its neighbours"),  # 7 periods since step 2: at most 2 + 2 x 7 + 2
        (19, 9, "by the mission's clock"),  # further: not plausible
        (1, 9, "by the mission's clock"),  # an old step
    ],
)
def test_a_resumed_node_rejoins_at_the_swarms_step_or_the_clocks(heard, step, how):
    """``OnboardPlanner.rejoin`` (no listening here: ``listen_s`` 0): the step heard of a
    neighbour when it is plausible, else the mission's clock's; its beliefs skip to it."""
    from mavlink_bridge.mission.onboard_planner import OnboardPlanner

    scenario = load_scenario("paper-10uav")
    starts = scenario.starts_for_seed(2)
    planner = OnboardPlanner(scenario, [starts[1]], 2, uav=1, link=None,
                             period_wall_s=lambda: 1.0)  # fmt: skip
    planner.beliefs.k = 3  # (as after the checkpoint of step 2)
    planner.swarm_step = heard
    assert planner.rejoin(3, lambda: 9, 30, listen_s=0.0) == (step, how)
    assert planner.beliefs.k == step and planner.stats.steps_missed == step - 3
