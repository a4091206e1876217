"""The daemon's mission as the mission view shows it (``mission_view``, docs/view.md): a step
listener (``DaemonOptions.step_listeners``) that turns each ``StepRecord``, the vehicles' link
state and the daemon's counters into a ``StepView``, and a progress hook that turns the daemon's
lines into the phase line and timeline events. It runs in the decision loop's thread and only
reads: the view's own thread does the rest (``mission_view.feed``)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

from mavlink_bridge.results.mission_result import StepRecord
from mavlink_bridge.vehicles.autopilot_adapter import autopilot_for
from mission_view.view_model import StepView, TimelineEvent, VehicleView
from mission_view.view_session import ViewSession
from planner.planner_interface import MODES

#: progress lines that go to the timeline, by the kind of event they are
LINE_KINDS = (("refused", "refusal"), ("warning", "warning"), ("lost", "link"), ("rejoin", "link"))


class DaemonViewFeed:
    """Feeds ``session`` from ``daemon`` (a ``MissionDaemon``). ``truth()``, when given,
    returns the true targets ``[[id, x_km, y_km, alive], ...]`` of a simulator, or None."""

    def __init__(
        self,
        daemon: Any,
        session: ViewSession,
        truth: Callable[[], list[list[float]] | None] | None = None,
    ) -> None:
        self.daemon = daemon
        self.session = session
        self.truth = truth
        self.pending: list[tuple[str, str]] = []  # (kind, text) said since the last step
        self.overrides: dict[str, int] = {}
        self.started: float | None = None  # wall clock of the first step

    def progress(self, text: str) -> None:
        """A line the daemon says (its ``progress`` callback)."""
        if not text:
            return
        lower = text.lower()
        kind = next((k for word, k in LINE_KINDS if word in lower), None)
        if kind is not None and self.daemon.phase == "decisions":
            self.pending.append((kind, text.removeprefix("warning: ")))
        else:
            self.session.phase(f"{self.daemon.phase}: {text}")

    def listener(self, record: StepRecord) -> None:
        """A ``StepListener``: one ``StepView`` per decision step."""
        daemon, step = self.daemon, record.status.step
        now = time.monotonic()
        if self.started is None:
            self.started = now
        link = daemon.link
        signed = None if link is None else link.signature_check is not None
        events = [TimelineEvent(step, kind, text) for kind, text in self.pending]
        self.pending = []
        for reason, count in daemon.account.overrides.items():
            new = count - self.overrides.get(reason, 0)
            if new > 0:
                events.append(
                    TimelineEvent(step, "override", f"envelope replaced {new} target(s): {reason}")
                )
        self.overrides = dict(daemon.account.overrides)
        for uav, target, value in record.engagements:
            x, y = (float(c) for c in record.positions_km[uav])
            text = f"engaged target {target} (value {value:g})"
            events.append(TimelineEvent(step, "engagement", text, int(uav), x, y))
        vehicles = []
        for i in range(daemon.n):
            v = daemon.vehicle(i)
            x, y = (float(c) for c in record.positions_km[i])
            fallback = float(record.headings[i]) * 45.0
            course = math.degrees(v.course_rad) if v.speed_mps > 1.0 else fallback
            mode = "" if record.modes is None else MODES[int(record.modes[i])]
            vehicles.append(
                VehicleView(
                    x,
                    y,
                    course,
                    active=bool(record.active[i]),
                    target_km=(float(record.aims_km[i, 0]), float(record.aims_km[i, 1])),
                    mode=autopilot_for(v).mode_name(v.custom_mode) if v.custom_mode >= 0 else "",
                    planner_mode=mode,
                    ground_speed_mps=v.speed_mps,
                    airspeed_mps=float(record.speeds_mps[i]),
                    last_heard_s=max(0.0, v.silent_for(now)),
                    signed=signed,
                    done=bool(record.done[i]),
                )  # fmt: skip
            )
        status = record.status
        view = StepView(
            step, vehicles, coverage=status.coverage, engaged=status.engaged,
            engaged_value=status.engaged_value, late=record.late,
            late_steps=daemon.account.late_steps, wall_s=now - self.started,
            truth=None if self.truth is None else self.truth(), events=events,
        )  # fmt: skip
        self.session.post(view, record.planner)
