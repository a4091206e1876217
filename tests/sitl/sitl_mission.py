"""A whole mission against ArduPlane SITL, for tests and benchmarks/bench_sitl.py.

``fly_sitl_mission`` starts N ArduPlane SITL instances (``sitl_harness.SitlSwarm``) at the
scenario's start cells, the payload simulator (``swarmplan payload``) on each instance's SERIAL1
and the daemon (``swarmplan daemon``) on each SERIAL0, waits (bounded) for the daemon's end, and
returns what it printed (with the wall time of each line), its result.json and the payload
simulator's summary. Every process it started is stopped on the way out, whatever happens.

``measure`` turns a run into the numbers docs/sitl.md reports: time to ready (wall s from the
daemon's start to ``armed N vehicles``; the arm phase's own wall time and the vehicles' clocks,
s since boot, when they were armed), distance of each plane from its planned cell centre at
the next decision, looks, engagements, violations, the safety account along every position
report per phase (``track_audit``: mission, hold, failsafe, RTL), the vehicles lost and back
(``link_events``), who was sent home, and the decision steps' length on the vehicles' clock
(the daemon's ``look_times_ms``: each step's look time stamp).
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import threading
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")

import numpy as np  # noqa: E402
from loopback import env, stop  # noqa: E402
from sitl_harness import SitlSwarm, homes_for_scenario  # noqa: E402

from planner.scenario import Scenario, load_scenario  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
#: the daemon's line at the end of its arm phase
ARMED = re.compile(
    r"armed \d+ vehicles after (?P<wall>[\d.]+) s \(vehicle clocks (?P<first>[\d.]+)\.\."
    r"(?P<last>[\d.]+) s since boot\)"
)


@dataclass
class Printed:
    """A process's output lines, each with the wall time (s since the start) it was read."""

    lines: list[tuple[float, str]] = field(default_factory=list)

    def first(self, text: str) -> float | None:
        return next((t for t, line in self.lines if text in line), None)

    def text(self) -> str:
        return "\n".join(line for _, line in self.lines)


@dataclass
class SitlMissionRun:
    returncode: int | None
    result: dict | None
    payload: dict | None
    daemon: Printed
    payload_printed: Printed
    wall_s: float
    out: Path
    planes: int
    speedup: float
    step_s: float
    daemon_process: subprocess.Popen | None = None  # while it runs (to signal it)

    def explain(self) -> str:
        """What to show when a test fails: the daemon's last lines and the payload's."""
        tail = "\n".join(line for _, line in self.daemon.lines[-40:])
        side = "\n".join(line for _, line in self.payload_printed.lines[-5:])
        return f"daemon exit {self.returncode}:\n{tail}\npayload:\n{side}"


def _read_lines(proc: subprocess.Popen, sink: Printed, started: float) -> threading.Thread:
    def read() -> None:
        assert proc.stdout is not None
        for raw in proc.stdout:
            sink.lines.append((time.monotonic() - started, raw.rstrip("\n")))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    return reader


def _start(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "swarmplan", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        text=True,
        env=env(PYTHONUNBUFFERED="1"),
        cwd=REPO,
    )


def scenario_with_planes(name: str, planes: int, folder: Path) -> str:
    """The built-in scenario ``name`` as it is for its own UAV count; for another count a copy in
    ``folder`` with ``planes`` starts spread in a row along the south edge, heading north."""
    scenario = load_scenario(name)
    if planes == scenario.uav_count:
        return name
    text = (REPO / "planner" / "scenarios" / f"{name}.toml").read_text()
    data = tomllib.loads(text)
    nx = data["parameters"]["grid_nx"]
    if planes > nx - 2:
        raise ValueError(f"{name} has room for at most {nx - 2} planes in a row")
    body = text.replace(f"count = {scenario.uav_count}", f"count = {planes}")
    body = body.split("[[uavs.start]]")[0].rstrip() + "\n"
    rest = text[text.index("[[targets]]") :]
    starts = "".join(
        f"\n[[uavs.start]]\nx_km = {int((k + 0.5) * nx / planes) + 0.5}\ny_km = 1.5\n"
        f"heading_deg = 90\n"
        for k in range(planes)
    )
    path = folder / f"{name}-{planes}.toml"
    path.write_text(body + starts + "\n" + rest)
    load_scenario(str(path))  # refuse a broken copy here, not in the daemon
    return str(path)


def fly_sitl_mission(
    binary: Path,
    workdir: Path,
    *,
    planes: int = 3,
    speedup: float = 10.0,
    scenario: str = "arduplane-3uav",
    steps: int | None = None,
    seed: int = 1,
    timeout_s: float = 300.0,
    params: dict[str, float] | None = None,
    daemon_args: list[str] | None = None,
    with_payload: bool = True,
) -> SitlMissionRun:
    """Fly one mission (module docstring). ``timeout_s`` bounds the daemon's whole run (wall)."""
    workdir.mkdir(parents=True, exist_ok=True)
    spec = scenario_with_planes(scenario, planes, workdir)
    loaded: Scenario = load_scenario(spec)
    out = workdir / "out"
    daemon_printed, payload_printed = Printed(), Printed()
    procs: list[subprocess.Popen] = []
    readers: list[threading.Thread] = []
    # the threat zones the daemon uploads are enforced (with no zone, ArduPlane refuses to arm
    # with FENCE_ENABLE 1: "Fences enabled, but none selected")
    sitl_params = {"FENCE_ENABLE": int(bool(loaded.threats)), **(params or {})}
    started = time.monotonic()
    returncode = None
    with SitlSwarm(
        binary, homes_for_scenario(loaded, seed), speedup=speedup, params=sitl_params,
        workdir=workdir / "sitl",
    ) as swarm:  # fmt: skip
        try:
            if with_payload:
                payload = _start(
                    ["payload", "--scenario", spec, "--seed", str(seed),
                     *swarm.payload_args()]
                )  # fmt: skip
                procs.append(payload)
                readers.append(_read_lines(payload, payload_printed, started))
            daemon = _start(
                ["daemon", "--scenario", spec, "--seed", str(seed), "--time-scale", f"{speedup:g}",
                 "--out", str(out), "--no-view", *(["--steps", str(steps)] if steps else []),
                 *swarm.connect_args(), *(daemon_args or [])]
            )  # fmt: skip
            procs.append(daemon)
            readers.append(_read_lines(daemon, daemon_printed, started))
            try:
                returncode = daemon.wait(timeout_s)
            except subprocess.TimeoutExpired:
                returncode = None
        finally:
            for proc in reversed(procs):
                stop(proc, 10.0)
            # every line read, the payload simulator's summary at its exit included (read
            # right after the stop, it was missing now and then)
            for reader in readers:
                reader.join(5)
    # what each printed, with the wall time of each line, beside the run's files
    for name, printed in (("daemon", daemon_printed), ("payload", payload_printed)):
        lines = (f"{t:8.1f}  {line}\n" for t, line in printed.lines)
        (workdir / f"{name}.log").write_text("".join(lines))
    result_path = out / "result.json"
    result = json.loads(result_path.read_text()) if result_path.is_file() else None
    summary = None
    for _, line in reversed(payload_printed.lines):
        if line.startswith("{"):
            summary = json.loads(line)
            break
    return SitlMissionRun(
        returncode, result, summary, daemon_printed, payload_printed,
        time.monotonic() - started, out, planes, speedup, loaded.config.step_s,
    )  # fmt: skip


def measure(run: SitlMissionRun) -> dict:
    """The numbers of a run (module docstring); None where the run did not produce them."""
    r = run.result or {}
    numbers: dict = {
        "planes": run.planes,
        "speedup": run.speedup,
        "exit": run.returncode,
        "wall_s": round(run.wall_s, 1),
        "time_to_ready_wall_s": run.daemon.first(f"armed {run.planes} vehicles"),
        "steps": r.get("steps"),
        "coverage": r.get("coverage"),
        "engaged": r.get("engaged_count"),
        "violations": r.get("violations"),
        "min_separation_km": r.get("min_separation_km"),
        "late_steps": r.get("late_steps"),
        "looks_missed": r.get("looks_missed"),
        "refused_commands": r.get("refused_commands"),
        "uavs_without_camera": r.get("uavs_without_camera"),
        "looks": (run.payload or {}).get("looks_sent"),
        "targets_engaged_truth": (run.payload or {}).get("targets_engaged"),
    }
    # the safety account along every position report, per phase (mission, hold, failsafe, RTL)
    audit = r.get("track_audit") or {}
    for phase, f in [("all", audit.get("all")), *(audit.get("phases") or {}).items()]:
        if f:
            numbers[f"track_{phase}"] = (
                f"threat entries {f['threat_entries']}, separation breaches "
                f"{f['separation_breaches']}, min separation {f['min_separation_km']} km, "
                f"min threat margin {f['min_threat_margin_km']} km"
            )
    numbers["lost"] = [
        f"vehicle {e['system_id']} {e['event']} at step {e['step']}"
        + (f" ({e['reason']})" if e.get("reason") else "")
        for e in r.get("link_events") or []
    ]
    numbers["rtl_sent_to"] = r.get("rtl_sent_to")
    numbers["rtl_not_sent"] = r.get("rtl_not_sent")
    armed = next((line for _, line in run.daemon.lines if ARMED.search(line)), None)
    if armed is not None:
        found = ARMED.search(armed)
        assert found is not None
        numbers["arm_phase_wall_s"] = float(found["wall"])
        numbers["armed_at_vehicle_s"] = [float(found["first"]), float(found["last"])]
    if ready := numbers["time_to_ready_wall_s"]:
        numbers["time_to_ready_wall_s"] = round(ready, 1)
    misses = []
    for uav in r.get("uavs", []):
        track, planned = uav.get("track_km") or [], uav.get("planned_km") or []
        for k in range(min(len(planned), len(track) - 1)):
            (x, y), (px, py) = track[k + 1], planned[k]
            misses.append(math.hypot(x - px, y - py))
    if misses:
        misses.sort()
        numbers["miss_km_mean"] = round(sum(misses) / len(misses), 3)
        numbers["miss_km_p95"] = round(misses[int(0.95 * (len(misses) - 1))], 3)
        numbers["miss_km_max"] = round(misses[-1], 3)
    # the decision instants on the vehicles' clock: each step's look time stamp (the daemon's)
    instants = [ms for _, ms in r.get("look_times_ms") or []]
    numbers.update(turn_breaks_by_step_length(r, run.step_s))
    gaps = [(b - a) / 1000.0 for a, b in zip(instants[1:], instants[2:], strict=False)]
    # each plane's clock drift from the wall clock x the speedup (the track audit's estimate):
    # SITL instances starved by a loaded machine run below their speedup by different amounts,
    # and a step's look stamps (each plane's own clock) then no longer make one time line
    numbers["clock_drift_s"] = audit.get("clock_drift_s")
    if gaps and min(gaps) < 0:
        numbers["step_s_vehicle"] = "n/a: the planes' clocks drifted apart (clock_drift_s)"
    elif gaps:  # from step 1 on: step 0 is the first instant after take-off, not a period
        numbers["step_s_vehicle_mean"] = round(sum(gaps) / len(gaps), 2)
        numbers["step_s_vehicle_min"] = round(min(gaps), 2)
        numbers["step_s_vehicle_max"] = round(max(gaps), 2)
        numbers["step_drift_s_max"] = round(max(abs(g - run.step_s) for g in gaps), 2)
    return numbers


def _heading_change_deg(a: np.ndarray, b: np.ndarray) -> float:
    turn = math.atan2(b[1], b[0]) - math.atan2(a[1], a[0])
    return math.degrees(abs((turn + math.pi) % (2 * math.pi) - math.pi))


def turn_breaks_by_step_length(result: dict, step_s: float, tolerance_deg: float = 15.0) -> dict:
    """The turn rule's breaks (the recorder's C_m on the flown positions at the decision steps,
    with the daemon's default tolerance) split three ways: ``planned`` where the plan itself
    turned more than the rule allows or kept the plane on its cell (a circle the planner asked
    for: a suspect circled for more looks, a hold beside a confirmed target before it is
    engaged; ``planned_km`` of the same steps), else by the length of the two steps around
    them: both within 10 % of ``step_s`` (``regular``), or not (a step after a stall of the
    machine, or the short one catching up after it, where a plane circled its target
    meanwhile)."""
    times = dict(result.get("look_times_ms") or [])
    limit = result["max_turn_deg"] + tolerance_deg
    regular = irregular = planned = 0
    for uav in result.get("uavs", []):
        track = np.asarray(uav.get("track_km") or [], float).reshape(-1, 2)
        plan = np.asarray(uav.get("planned_km") or [], float).reshape(-1, 2)
        legs = np.diff(track, axis=0)
        last = None  # the last leg flown (as the recorder: a standstill keeps it)
        for k in range(len(legs)):
            if np.hypot(*legs[k]) <= 1e-9:
                continue
            if last is None:
                last = k
                continue
            turn = _heading_change_deg(legs[last], legs[k])
            previous, last = last, k
            if turn <= limit:
                continue
            # the planned legs of the same steps: position k + 1 was planned at step k
            if previous >= 1 and k < len(plan):
                before, after = plan[previous] - plan[previous - 1], plan[k] - plan[k - 1]
                still = min(np.hypot(*before), np.hypot(*after)) <= 1e-9
                if still or _heading_change_deg(before, after) > limit:
                    planned += 1
                    continue
            spans = [
                (times[j] - times[j - 1]) / 1000.0
                for j in (previous + 1, k + 1)
                if j in times and j - 1 in times and j - 1 > 0
            ]
            if all(abs(span - step_s) <= 0.1 * step_s for span in spans):
                regular += 1
            else:
                irregular += 1
    return {
        "turn_breaks_regular_steps": regular,
        "turn_breaks_around_stalls": irregular,
        "turn_breaks_planned": planned,
    }
