"""What a mission run tells the world: the per-step record its listeners get, the link events,
the daemon's own counters, and the result dict (``planner.metrics.MissionRecorder``'s, as in
``swarmplan run``, plus the fields only a MAVLink run has).

Listeners (``DaemonOptions.step_listeners``) receive one :class:`StepRecord` after every decision
step: copies of the step's arrays, and the planner itself, to be read and never changed (a live
view takes its beliefs from it; the planner stays free of I/O).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

ALGORITHM = "hapf-aco"


@dataclass
class StepStatus:
    """What one decision step did (for a progress display)."""

    step: int
    steps: int
    active: int
    lost: list[int]
    coverage: float
    engaged: int
    engaged_value: float
    overrides: int


@dataclass(frozen=True)
class StepRecord:
    """A read-only snapshot of one decision step, for step listeners (live view, audits).

    Positions in km in the mission frame; arrays are copies. ``planner`` is the planner after
    this step: read it, never change it."""

    status: StepStatus
    positions_km: np.ndarray  # (N, 2) measured at the decision instant
    positions_ms: np.ndarray  # (N,) the vehicle's clock (time_boot_ms) at that position
    cells: np.ndarray  # (N, 2) the cell each UAV is in
    headings: np.ndarray  # (N,)
    next_cells: np.ndarray  # (N, 2) the cells sent (after both envelopes)
    aims_km: np.ndarray  # (N, 2) the guided targets
    speeds_mps: np.ndarray  # (N,) the leg airspeeds
    active: np.ndarray  # (N,) bool
    done: np.ndarray  # (N,) bool
    engage: np.ndarray  # (N,) bool: engagement requested this step
    late: bool  # paced time: this step's commands went out late
    planner: Any = None
    #: engagements acknowledged this step: (UAV, target id, value); and the planner's mode of
    #: each UAV (index into planner.planner_interface.MODES), for the mission view's timeline
    #: and table
    engagements: tuple[tuple[int, int, float], ...] = ()
    modes: np.ndarray | None = None
    #: the envelope's replacements this step: (UAV, reason)
    overrides: tuple[tuple[int, str], ...] = ()


StepListener = Callable[[StepRecord], None]


class LookTimes:
    """Per decision step, the vehicles' clock (``time_boot_ms``) at the looks it used: the most
    common stamp over the active vehicles. It joins a simulator's ground truth, whose steps
    count from the simulator's boot, to the daemon's steps, which count from the take-off
    (``sim_gateway.target_account.align_steps``); the result keeps it as ``look_times_ms``."""

    def __init__(self) -> None:
        self.by_step: dict[int, int] = {}

    def note(self, step: int, positions_ms: np.ndarray, active: np.ndarray) -> None:
        stamps = positions_ms[active & (positions_ms > 0)]
        if stamps.size:
            values, counts = np.unique(stamps.astype(np.int64), return_counts=True)
            self.by_step[int(step)] = int(values[np.argmax(counts)])

    def rows(self) -> list[list[int]]:
        """``[[step, time_boot_ms], ...]`` in step order (JSON-ready)."""
        return [[s, ms] for s, ms in sorted(self.by_step.items())]


@dataclass
class LinkEvent:
    step: int
    uav: int
    event: str  # "lost", "back" (heard again but not fit to rejoin: disarmed, ...), "rejoined"
    wall_s: float
    reason: str = ""  # why it was lost ("silent 3.2 s", "link closed", "disarmed", ...)


@dataclass
class MissionAccount:
    """The daemon's own counters (carried across a restart by the checkpoint)."""

    overrides: dict[str, int] = field(
        default_factory=lambda: {
            "area": 0,
            "threat": 0,
            "separation": 0,
            "range": 0,
            "predicted_threat": 0,
            "predicted_separation": 0,
        }
    )
    refused_commands: int = 0
    looks_missed: int = 0
    late_steps: int = 0
    events: list[LinkEvent] = field(default_factory=list)
    #: UAVs found to have no camera (engagements turned off for them; decision_step.py)
    cameraless: list[int] = field(default_factory=list)


@dataclass
class MissionReport:
    """The result dict (same fields as ``swarmplan run``) and the daemon's own account."""

    result: dict[str, Any]
    events: list[LinkEvent] = field(default_factory=list)


def link_event_rows(events: list[LinkEvent], labels: list[int | str]) -> list[dict[str, Any]]:
    """The events as result.json lists them; ``labels``: each UAV's vehicle as
    ``VehicleKey.label`` names it (its system id on one network, else "LINK:SYSID")."""
    rows = []
    for e in events:
        row: dict[str, Any] = {"step": e.step, "uav": e.uav, "system_id": labels[e.uav]}
        row["event"] = e.event
        if e.reason:
            row["reason"] = e.reason
        rows.append(row)
    return rows


def lost_vehicle_lines(result: dict[str, Any]) -> list[str]:
    """The lost vehicles of a result, each with what happened to it (``link_events``) and, when it
    was not sent home, why (``rtl_not_sent``): for the summary a person reads."""
    lost = result.get("lost_uavs") or []
    if not lost:
        return []
    names = result.get("vehicles")  # more than one network: "LINK:SYSID" by UAV

    def name(uav: int) -> str:
        return str(names[uav]) if names else str(uav + 1)

    lines = [f"lost vehicles   {', '.join(name(i) for i in lost)} (system ids)"]
    for uav in lost:
        said = []
        for e in result.get("link_events") or []:
            if e["uav"] == uav:
                reason = f" ({e['reason']})" if e.get("reason") else ""
                said.append(f"{e['event']} at step {e['step']}{reason}")
        last = next(
            (e["event"] for e in reversed(result.get("link_events") or []) if e["uav"] == uav),
            None,
        )
        if last == "back":
            said.append("not launched again mid-mission")
        why_not = (result.get("rtl_not_sent") or {}).get(name(uav))
        if why_not:
            said.append(f"no RTL: {why_not}")
        lines.append(f"  vehicle {name(uav):<5s} {'; '.join(said)}")
    return lines


def mavlink_extra(
    account: MissionAccount,
    link: Any,
    tlog: str | None,
    resumed_from_step: int | None,
    labels: list[int | str],
) -> dict[str, Any]:
    """The result fields only a MAVLink run has (docs/daemon.md, "What the result measures").
    ``labels``: each UAV's vehicle (``VehicleKey.label``); with more than one network they are
    listed as ``vehicles`` ("LINK:SYSID" by UAV index), else the system id is UAV + 1."""
    named = {"vehicles": labels} if any(isinstance(x, str) for x in labels) else {}
    return {
        "source": "mavlink",
        "endpoints": link.describe(),
        "envelope_overrides": dict(account.overrides),
        "refused_commands": account.refused_commands,
        "looks_missed": account.looks_missed,
        "late_steps": account.late_steps,
        "uavs_without_camera": sorted(account.cameraless),
        "link_events": link_event_rows(account.events, labels),
        "lost_uavs": sorted({e.uav for e in account.events if e.event == "lost"}),
        "frames_received": link.messages_received,
        "stale_positions": link.plausibility.counts.stale_positions,
        "plausibility": link.plausibility.counts.as_dict(),
        "signing": None if link.signature_check is None else link.signature_check.counters(),
        "resumed_from_step": resumed_from_step,
        "tlog": tlog,
        **named,
    }
