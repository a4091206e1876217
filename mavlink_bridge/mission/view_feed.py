"""The daemon's mission as the mission view shows it (``mission_view``, docs/view.md): a step
listener (``DaemonOptions.step_listeners``) that turns each ``StepRecord``, the vehicles' state
(link, mode, altitude, battery, GPS, home, looks) and the daemon's counters into a ``StepView``,
and a progress hook that turns the daemon's lines into the phase line (launch, search, return,
each from the step it began at) and timeline events. It runs in the decision loop's thread and
only reads: the view's own thread does the rest (``mission_view.feed``)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

from mavlink_bridge.mission.operator_actions import SENT_HOME
from mavlink_bridge.results.mission_result import StepRecord
from mavlink_bridge.vehicles.autopilot_adapter import autopilot_for
from mission_view.view_model import StepView, TimelineEvent, VehicleView
from mission_view.view_session import ViewSession
from planner.geodesy import geodetic_to_local_km
from planner.planner_interface import MODES

#: progress lines that go to the timeline, by the kind of event they are
LINE_KINDS = (
    ("operator (", "operator"),  # an operator's action (operator_actions.py)
    (SENT_HOME, "operator"),  # a plane it sent home, out of the mission (not a lost link)
    ("refused", "refusal"),
    ("warning", "warning"),
    ("lost", "link"),
    ("rejoin", "link"),
)

#: how the page names why a plane left the mission for good (``LossWatch.retired``); any other
#: reason (a resumed daemon's: "sent home at the resume") as it is
SENT_HOME_LABELS = {SENT_HOME: "sent home (operator)"}

#: the mission's stage an operator thinks in, by the daemon's phase (any other: the launch)
STAGES = {"decisions": "search", "rtl": "return"}
#: the phase line from the first decision step on
SEARCH_LINE = "search: the planner flies the swarm"


def phase_line(daemon_phase: str, text: str) -> str:
    """``launch (take off): airborne, GUIDED``, ``search: ...``, ``return: RTL sent ...``."""
    stage = STAGES.get(daemon_phase)
    return f"{stage}: {text}" if stage else f"launch ({daemon_phase}): {text}"


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
        self.searching = False  # the search's phase line is said
        self.homes: dict[tuple[float, float], tuple[float, float]] = {}  # lat/lon -> km

    def progress(self, text: str) -> None:
        """A line the daemon says (its ``progress`` callback)."""
        if not text:
            return
        lower = text.lower()
        kind = next((k for word, k in LINE_KINDS if word in lower), None)
        if kind is not None and self.daemon.phase == "decisions":
            self.pending.append((kind, text.removeprefix("warning: ")))
        else:
            self.session.phase(phase_line(self.daemon.phase, text))

    def listener(self, record: StepRecord) -> None:
        """A ``StepListener``: one ``StepView`` per decision step."""
        daemon, step = self.daemon, record.status.step
        now = time.monotonic()
        if self.started is None:
            self.started = now
        if not self.searching:
            self.searching = True
            self.session.phase(SEARCH_LINE, step)
        events = [TimelineEvent(step, kind, text) for kind, text in self.pending]
        self.pending = []
        events += self.override_events(record)
        for uav, target, value in record.engagements:
            x, y = (float(c) for c in record.positions_km[uav])
            text = f"engaged target {target} (value {value:g})"
            events.append(TimelineEvent(step, "engagement", text, int(uav), x, y))
        vehicles = [self.vehicle_view(record, i, now) for i in range(daemon.n)]
        status = record.status
        view = StepView(
            step, vehicles, coverage=status.coverage, engaged=status.engaged,
            engaged_value=status.engaged_value, late=record.late,
            late_steps=daemon.account.late_steps, wall_s=now - self.started,
            truth=None if self.truth is None else self.truth(), events=events,
        )  # fmt: skip
        self.session.post(view, record.planner)

    def override_events(self, record: StepRecord) -> list[TimelineEvent]:
        """The envelope's replacements of the step, one event per UAV and reason (from the
        record); any counted but not named (an older daemon part) as one swarm-wide event."""
        step, named = record.status.step, dict[tuple[int, str], int]()
        for uav, reason in record.overrides:
            named[(uav, reason)] = named.get((uav, reason), 0) + 1
        events = [
            TimelineEvent(step, "override", f"envelope replaced its target: {reason}"
                          + (f" ({count}x)" if count > 1 else ""), int(uav))
            for (uav, reason), count in named.items()
        ]  # fmt: skip
        counters = self.daemon.account.overrides
        for reason, count in counters.items():
            said = sum(c for (_, r), c in named.items() if r == reason)
            new = count - self.overrides.get(reason, 0) - said
            if new > 0:
                text = f"envelope replaced {new} target(s): {reason}"
                events.append(TimelineEvent(step, "override", text))
        self.overrides = dict(counters)
        return events

    def vehicle_view(self, record: StepRecord, i: int, now: float) -> VehicleView:
        """UAV ``i`` at the step: the record's plan and the vehicle's reported state."""
        v = self.daemon.vehicle(i)
        link = self.daemon.link
        x, y = (float(c) for c in record.positions_km[i])
        fallback = float(record.headings[i]) * 45.0
        course = math.degrees(v.course_rad) if v.speed_mps > 1.0 else fallback
        look = v.looks.get(v.latest_look)
        return VehicleView(
            x, y, course,
            active=bool(record.active[i]),
            target_km=(float(record.aims_km[i, 0]), float(record.aims_km[i, 1])),
            mode=autopilot_for(v).mode_name(v.custom_mode) if v.custom_mode >= 0 else "",
            planner_mode="" if record.modes is None else MODES[int(record.modes[i])],
            ground_speed_mps=v.speed_mps,
            airspeed_mps=float(record.speeds_mps[i]),
            last_heard_s=max(0.0, v.silent_for(now)),
            signed=None if link is None else link.signature_check is not None,
            done=bool(record.done[i]),
            alt_m=v.relative_alt_m if v.has_position else None,
            battery_pct=v.battery_pct if v.battery_pct >= 0 else None,
            gps_fix=v.gps_fix_type if v.gps_fix_type >= 0 else None,
            home_km=self.home_km(v.home),
            last_look=None if look is None else look.index,
            last_look_s=None if look is None else max(0.0, now - look.received_s),
            sent_home=self.sent_home(i),
        )  # fmt: skip

    def sent_home(self, i: int) -> str | None:
        """Why UAV ``i`` is out of the mission for good and on its way home (the operator sent
        it, or a resumed daemon did), or None: a plane sent home is not a lost one."""
        why = self.daemon.loss.retired.get(i)
        return None if why is None else SENT_HOME_LABELS.get(why, why)

    def home_km(self, home: tuple[float, float, float] | None) -> tuple[float, float] | None:
        """A vehicle's home in the mission frame (converted once per home)."""
        if home is None:
            return None
        key = (home[0], home[1])
        if key not in self.homes:
            x, y = geodetic_to_local_km(home[0], home[1], self.daemon.scenario.origin)
            self.homes[key] = (float(x[0]), float(y[0]))
        return self.homes[key]
