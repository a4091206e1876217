"""A whole mission against PX4 SITL (and ArduPlane SITL beside it), for tests and benchmarks.

``fly_px4_mission`` starts the scenario's planes: the first ``arduplane`` of them as ArduPlane
SITL instances (``sitl_harness.SitlSwarm``, system ids 1..a; idle until a client connects),
the rest as PX4 SIH airplanes (``px4_harness.Px4Swarm``, system ids a+1..n), each at its start
cell; the payload simulator (``swarmplan payload``) on every plane's second link (ArduPlane's
SERIAL1, PX4's onboard link, which PX4 forwards to its GCS link) and the daemon (``swarmplan
daemon``) on every plane's GCS link. PX4 (and then the payload simulator, which speaks to PX4
only once PX4 is there to answer) is launched once the daemon listens, i.e. after it has
measured its own pace on this machine. ``during(run, swarms)``, when given, runs in a thread
while the daemon flies (e.g. to kill a plane at a step). Waits (bounded) for the daemon's end
and returns a ``sitl_mission.SitlMissionRun``; every process it started is stopped on the way
out.

``modes_seen`` reads, from the daemon's tlog (what came over the wire), the modes each plane's
autopilot reported in its heartbeats, by name (the autopilot's adapter names them).
"""

from __future__ import annotations

import contextlib
import json
import re
import subprocess
import threading
import time
import tomllib
from collections.abc import Callable
from pathlib import Path

from loopback import stop
from px4_harness import Px4Swarm
from pymavlink import mavutil
from sitl_harness import SitlSwarm, homes_for_scenario
from sitl_mission import REPO, Printed, SitlMissionRun, _read_lines, _start

from mavlink_bridge.vehicles.autopilot_adapter import adapter_for_autopilot
from planner.scenario import load_scenario


def scenario_with_starts(name: str, starts: list[tuple[float, float]], folder: Path) -> str:
    """A copy in ``folder`` of the built-in scenario ``name`` with these starts (km, heading
    north) instead of its own."""
    text = (REPO / "planner" / "scenarios" / f"{name}.toml").read_text()
    count = tomllib.loads(text)["uavs"]["count"]
    head = text.split("[[uavs.start]]")[0].replace(f"count = {count}", f"count = {len(starts)}")
    rest = text[text.index("[[targets]]") :]
    body = "".join(
        f"[[uavs.start]]\nx_km = {x:g}\ny_km = {y:g}\nheading_deg = 90\n\n" for x, y in starts
    )
    path = folder / f"{name}-{len(starts)}.toml"
    path.write_text(head.rstrip() + "\n\n" + body + rest)
    load_scenario(str(path))  # refuse a broken copy here, not in the daemon
    return str(path)


def searching_to_the_end(name: str, folder: Path) -> str:
    """A copy in ``folder`` of the built-in scenario ``name`` whose planner searches to the last
    step (``home_by_end`` off): a short mission that looks for targets, then RTL."""
    text = (REPO / "planner" / "scenarios" / f"{name}.toml").read_text()
    path = folder / f"{name}-searching.toml"
    path.write_text(text.replace("home_by_end = true", "home_by_end = false"))
    assert not load_scenario(str(path)).config.home_by_end
    return str(path)


def reached_step(run: SitlMissionRun, step: int) -> bool:
    """Has the daemon printed its line of decision step ``step``?"""
    return any(re.search(rf"step +{step}/", line) for _, line in list(run.daemon.lines))


def fly_px4_mission(
    px4_root: Path,
    workdir: Path,
    scenario: str,
    *,
    speedup: float = 5.0,
    steps: int | None = None,
    arduplane: int = 0,
    arduplane_binary: Path | None = None,
    with_payload: bool = True,
    payload_args: list[str] | None = None,
    daemon_args: list[str] | None = None,
    during: Callable[[SitlMissionRun, list], None] | None = None,
    timeout_s: float = 240.0,
    seed: int = 1,
) -> SitlMissionRun:
    """Fly one mission (module docstring). ``timeout_s`` bounds the daemon's whole run (wall)."""
    workdir.mkdir(parents=True, exist_ok=True)
    loaded = load_scenario(scenario)
    homes = homes_for_scenario(loaded, seed)
    out = workdir / "out"
    run = SitlMissionRun(
        None, None, None, Printed(), Printed(), 0.0, out, len(homes), speedup,
        loaded.config.step_s,
    )  # fmt: skip
    started = time.monotonic()
    with contextlib.ExitStack() as stack:
        swarms: list = []
        if arduplane:
            fence = {"FENCE_ENABLE": int(bool(loaded.threats))}
            swarms.append(stack.enter_context(SitlSwarm(
                arduplane_binary, homes[:arduplane], speedup=speedup, params=fence,
                workdir=workdir / "arduplane",
            )))  # fmt: skip
        px4 = Px4Swarm(
            px4_root, homes[arduplane:], speedup=speedup, workdir=workdir / "px4",
            first_system_id=arduplane + 1,
        )  # fmt: skip
        stack.callback(px4.stop)
        px4.claim()
        swarms.append(px4)
        procs, readers = [], []
        try:
            daemon = _start(
                ["daemon", "--scenario", scenario, "--seed", str(seed), "--time-scale",
                 f"{speedup:g}", "--out", str(out), "--no-view",
                 *(["--steps", str(steps)] if steps else []),
                 *[a for s in swarms for a in s.connect_args()], *(daemon_args or [])]
            )  # fmt: skip
            procs.append(daemon)
            run.daemon_process = daemon
            readers.append(_read_lines(daemon, run.daemon, started))
            # PX4 once the daemon has measured its own pace (``keeping_up.py``): three PX4
            # instances booting at 5x took that measure from 0.4 s a step to 3.8 and more
            deadline = time.monotonic() + timeout_s
            while daemon.poll() is None and time.monotonic() < deadline:
                if any("listening on" in line for _, line in list(run.daemon.lines)):
                    break
                time.sleep(0.1)
            px4.launch()
            if with_payload:
                links = [a for s in swarms for a in s.payload_args()]
                payload = _start([
                    "payload", "--scenario", scenario, "--seed", str(seed), *links,
                    *(payload_args or []),
                ])  # fmt: skip
                procs.append(payload)
                readers.append(_read_lines(payload, run.payload_printed, started))
            if during is not None:
                threading.Thread(target=during, args=(run, swarms), daemon=True).start()
            try:
                run.returncode = daemon.wait(timeout_s)
            except subprocess.TimeoutExpired:
                run.returncode = None
        finally:
            for proc in reversed(procs):
                stop(proc, 10.0)
            for reader in readers:
                reader.join(5)
    for name, printed in (("daemon", run.daemon), ("payload", run.payload_printed)):
        (workdir / f"{name}.log").write_text("".join(f"{t:8.1f}  {x}\n" for t, x in printed.lines))
    result_path = out / "result.json"
    run.result = json.loads(result_path.read_text()) if result_path.is_file() else None
    summaries = [x for _, x in run.payload_printed.lines if x.startswith("{")]
    run.payload = json.loads(summaries[-1]) if summaries else None
    run.wall_s = time.monotonic() - started
    return run


def modes_seen(tlog: Path) -> dict[int, list[str]]:
    """System id -> the modes its autopilot reported in HEARTBEATs, in order (changes only)."""
    log = mavutil.mavlink_connection(str(tlog))
    seen: dict[int, list[str]] = {}
    while (msg := log.recv_match(type="HEARTBEAT")) is not None:
        if msg.get_srcComponent() != 1 or msg.type == mavutil.mavlink.MAV_TYPE_GCS:
            continue
        name = adapter_for_autopilot(msg.autopilot).mode_name(msg.custom_mode)
        modes = seen.setdefault(msg.get_srcSystem(), [])
        if not modes or modes[-1] != name:
            modes.append(name)
    log.close()
    return seen
