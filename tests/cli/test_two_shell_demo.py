"""The two-shell example of docs/daemon.md (``swarmplan sim --lockstep & swarmplan daemon
--lockstep``, with their default scenario and seed) flies the very mission ``swarmplan demo``
flies: ``sim`` and ``daemon`` once defaulted to seed 0 while ``run`` and ``demo`` used 1;
``swarmplan account`` joins the simulator's ground truth to the daemon's result into the very
per-target account the demo gives; and the simulator's ground-truth safety account, which the
demo merges into result.json as ``simulator_truth``, is the two-shell user's too: the simulator
prints it (``safety``) in the JSON summary it ends with.

Both fly signed by default (issue 31, finding 4): the demo with a key made for the mission and
handed to its simulator in the environment (never on the command line, never in a file it
writes), the two shells with the key file the simulator makes (mode 0600) and the daemon reads.
A stranger sends unsigned forced disarms and RTL mode changes to every vehicle port of both
simulators throughout: nothing changes (the missions stay identical, every plane is airborne at
the end) and the simulators count the frames they dropped."""

from __future__ import annotations

import gzip
import json
import os
import stat
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import pytest
from loopback import free_udp_port, run_swarmplan, start_swarmplan, stop
from vehicle_spoofer import DisarmSpoofer, simulator_ports, swarmplan_sim_pid

from sim_gateway.target_account import align_steps
from swarmplan.arguments import DEFAULT_SEED
from swarmplan.demo import simulator_summary

STEPS = 12

#: The run's own bookkeeping, not the mission flown; and what only the demo joins in from the
#: simulator it runs (the daemon flies MAVLink vehicles: SITL or aircraft have no ground truth)
VOLATILE = {"wall_time_s", "endpoints", "frames_received", "tlog", "target_account", "signing"}
FROM_THE_SIMULATOR = {"simulator_truth"}
#: The simulator's ground truth, written when it stops (``swarmplan sim --target-account``).
TRUTH = "target_truth.json"


@dataclass
class Flown:
    """One way of flying the mission: the daemon's result, the simulator's summary, how many
    unsigned commands the stranger sent, and the daemon's (or demo's) stderr."""

    result: dict
    simulator: dict
    spoofed: int
    stderr: str


def _wait_for(path: Path, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not path.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert path.exists(), f"{path} was not made"


def two_shells(out: Path) -> tuple[Flown, Path]:
    """``swarmplan sim --lockstep --signing-key-file K`` in the background (it makes K), then
    ``swarmplan daemon --lockstep --signing-key-file K``, both with their defaults but for a free
    port (the docs use 14550) and a short mission, a stranger spoofing the simulator's vehicle
    ports meanwhile; then the simulator stopped as the docs say (Ctrl-C or ``kill``)."""
    port = free_udp_port()
    log, key = out.parent / "sim.log", out.parent / "mission.key"
    sim = start_swarmplan(
        ["sim", "--lockstep", "--gcs-port", str(port), "--target-account", str(out.parent / TRUTH),
         "--signing-key-file", str(key)],
        log,
    )  # fmt: skip
    try:
        spoofer = DisarmSpoofer(sim.pid, simulator_ports(sim.pid, log, 60))
        _wait_for(key, 10)
        spoofer.start()
        proc = run_swarmplan(
            ["daemon", "--lockstep", "--connect", f"udpin:127.0.0.1:{port}",
             "--steps", str(STEPS), "--no-view", "--json", "--out", str(out),
             "--signing-key-file", str(key)],
            timeout=150,
        )  # fmt: skip
        spoofer.stop()
    finally:
        stop(sim)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = simulator_summary(log)  # what the demo reads from its simulator
    assert summary is not None, log.read_text()[-2000:]
    return Flown(json.loads(proc.stdout), summary, spoofer.sent, proc.stderr), key


def demo(out: Path) -> tuple[Flown, str]:
    """``swarmplan demo`` with a stranger spoofing its simulator's vehicle ports; and the key
    the simulator got (read from its environment, as only its own user can)."""
    err = out.parent / "demo.err"
    out.parent.mkdir(parents=True, exist_ok=True)
    proc = start_swarmplan(
        ["demo", "--steps", str(STEPS), "--no-view", "--json", "--out", str(out)],
        err,
        stdout_pipe=True,
    )
    try:
        sim_pid = swarmplan_sim_pid(proc.pid, 60)
        assert sim_pid is not None, "the demo started no simulator"
        environ = Path(f"/proc/{sim_pid}/environ").read_bytes().split(b"\0")
        given = [v for v in environ if v.startswith(b"SWARMPLAN_SIGNING_KEY=")]
        assert len(given) == 1, "the demo's simulator got no signing key"
        key = given[0].split(b"=", 1)[1].decode()
        assert key.encode() not in Path(f"/proc/{sim_pid}/cmdline").read_bytes()
        spoofer = DisarmSpoofer(sim_pid, simulator_ports(sim_pid, out / "sim.log", 60))
        spoofer.start()
        stdout, _ = proc.communicate(timeout=150)
        spoofer.stop()
    finally:
        stop(proc)
    stderr = err.read_text(errors="replace")
    assert proc.returncode == 0, stderr[-2000:]
    summary = simulator_summary(out / "sim.log")
    assert summary is not None
    return Flown(json.loads(stdout), summary, spoofer.sent, stderr), key


def assert_spoofing_changed_nothing(flown: Flown) -> None:
    """Every plane still airborne when the simulator stopped (a forced disarm lands it at once),
    the mission flown to its end, the unsigned commands dropped and counted, not signed once."""
    assert flown.spoofed > 0
    assert flown.simulator["airborne"] == len(flown.result["uavs"])
    assert flown.result["steps"] == STEPS and not flown.result.get("lost_uavs")
    assert flown.spoofed >= flown.simulator["unsigned_refused"] >= flown.spoofed // 2
    assert flown.simulator["bad_signatures"] == 0
    assert flown.result["signing"]["signed_accepted"] > 0
    assert "flying unsigned" not in flown.stderr


def assert_key_nowhere(key_hex: str, folder: Path) -> None:
    """No file of the run folder (what users share) holds the key, as text or bytes."""
    raw = bytes.fromhex(key_hex)
    for path in folder.rglob("*"):
        if path.is_file():
            data = path.read_bytes()
            if path.suffix == ".gz":
                data = gzip.decompress(data)
            assert key_hex.encode() not in data.lower() and raw not in data, path


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs Linux's /proc")
@pytest.mark.timeout(200)
def test_the_docs_two_shell_example_reproduces_the_demo(tmp_path):
    (tmp_path / "shells").mkdir()
    with ThreadPoolExecutor(2) as pool:  # both lockstep: the load cannot change either result
        shells = pool.submit(two_shells, tmp_path / "shells" / "out")
        alone = pool.submit(demo, tmp_path / "demo" / "out")
        (flown_a, key_file), (flown_b, demo_key) = shells.result(), alone.result()
    a, b, simulator = flown_a.result, flown_b.result, flown_a.simulator
    # signed by default, and a stranger's unsigned disarms and mode changes changed nothing
    for flown in (flown_a, flown_b):
        assert_spoofing_changed_nothing(flown)
    assert stat.S_IMODE(os.stat(key_file).st_mode) == 0o600
    assert_key_nowhere(demo_key, tmp_path / "demo")
    assert_key_nowhere(key_file.read_text().strip(), tmp_path / "shells" / "out")
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
    assert simulator["safety"] == flown_b.simulator["safety"] == b["simulator_truth"]


def test_every_command_defaults_to_one_seed():
    from swarmplan.cli import build_parser

    parser = build_parser()
    for command in (["run", "paper-2uav"], ["demo"], ["sim"], ["daemon"]):
        assert parser.parse_args(command).seed == DEFAULT_SEED, command
