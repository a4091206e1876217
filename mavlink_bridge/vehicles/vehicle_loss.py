"""Loss and return of one vehicle: one vehicle's failure stays one vehicle's.

A vehicle is **lost** when

* its link went away (a TCP connection closed or failed: ``Endpoint.closed_reason``; the
  endpoint reconnects with backoff, ``links.py``),
* it has been silent for ``lost_after_s`` wall seconds, or,
* once the decision loop runs, it is no longer armed or no longer in GUIDED (seen on two
  heartbeats in a row: one late heartbeat from before the switch to GUIDED is not a mode change;
  a plane that lands disarms or leaves GUIDED).

A lost vehicle is inactive to the planner and gets no commands; the others go on. It **rejoins**
when it is heard again (within ``min(1, lost_after_s / 2)`` s), its link is up, and, in the
loop, it is armed and in GUIDED. Both events are said and kept (``MissionAccount.events``,
``LinkEvent`` with the reason).

A vehicle lost with its link or to silence that is heard again, but disarmed or out of GUIDED,
is **back but still lost**, said once with what it is now (``LinkEvent`` "back"): an autopilot
that rebooted mid-mission (an ArduPlane SITL instance restarted) comes back disarmed on the
ground. The daemon does not launch it again: a take-off into a swarm in flight is not judged by
the flight envelope (it plans legs of airborne planes, not a climb-out through their paths).
Armed and in GUIDED again (flown up by its pilot), it rejoins. Silence is counted in wall
seconds because a silent vehicle has no clock of its own to count with: its last report's
``time_boot_ms`` stands still, and the other vehicles' clocks are not its own.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from mavlink_bridge.results.mission_result import LinkEvent, MissionAccount
from mavlink_bridge.vehicles.autopilot_adapter import autopilot_for
from mavlink_bridge.vehicles.vehicle_state import VehicleState

#: the reasons a vehicle went away (rather than being in the wrong state)
GONE = ("link ", "silent ")

#: lockstep: no vehicle heard for this long (wall s) is a pause of the whole simulator, not loss
PAUSE_AFTER_S = 0.5


@dataclass
class SwarmPauses:
    """Wall-clock intervals in which no vehicle at all was heard (lockstep: the simulator, or the
    machine, paused; simulated time stood still). A vehicle's silence does not count them."""

    intervals: list[list[float]] = field(default_factory=list)  # [start, end], the last open
    open: bool = False

    def note(self, now: float, newest_heard: float) -> None:
        """Called as the link is watched: ``newest_heard`` is when any vehicle was last heard."""
        if self.open and newest_heard > self.intervals[-1][0]:
            self.intervals[-1][1] = newest_heard  # heard again: the pause is over
            self.open = False
        if not self.open and now - newest_heard > PAUSE_AFTER_S:
            self.intervals.append([newest_heard, now])
            self.open = True
        elif self.open:
            self.intervals[-1][1] = now
        self.intervals = [iv for iv in self.intervals if iv[1] > now - 300.0]

    def within(self, start: float, end: float) -> float:
        """Wall seconds of pauses between ``start`` and ``end``."""
        return sum(max(0.0, min(b, end) - max(a, start)) for a, b in self.intervals)


def paced_lost_after_s(speedup: float) -> float:
    """Wall seconds of silence before a vehicle counts as lost, for a simulator paced at
    ``speedup`` on this machine (``swarmplan demo --speedup``): 200 s of the vehicles' clock, but
    at least 1 wall s and at most 10. The cap: at 1x, 200 s of
    silence is a third of a mission planned for a vehicle that may be gone, while a stall of the
    shared machine (the simulator, the daemon and the live view on one machine) lasts seconds of
    wall time at any speedup; 10 s rides out the stalls measured under load (the paced tests use
    ``--lost-after 10`` at 20x). The daemon's own default, 3 wall s, does not scale: against
    aircraft and SITL a silence is a link's or a machine's, both wall time."""
    return max(1.0, min(10.0, 200.0 / speedup))


def link_down(v: VehicleState) -> str | None:
    """Why the link to ``v`` is down now (its endpoint closed), or None."""
    link = v.link
    return None if link is None else link.endpoint.closed_reason


@dataclass
class LossWatch:
    """Marks vehicles lost and rejoined (see the module docstring). ``vehicles()`` lists the
    expected vehicles, index = UAV; ``in_mission()`` tells whether the decision loop runs (only
    then are disarmed or non-GUIDED vehicles lost)."""

    vehicles: Callable[[], list[VehicleState]]
    account: MissionAccount
    lost_after_s: float
    in_mission: Callable[[], bool]
    say: Callable[[str], None] = lambda text: None
    reasons: dict[int, str] = field(default_factory=dict)  # UAV -> why it is lost now
    #: lockstep: whole-swarm silences (the simulator or the machine paused, simulated time stood
    #: still), which count as no one's silence
    pauses: SwarmPauses | None = None
    #: UAV -> why it was sent home for the rest of the mission (``retire``)
    retired: dict[int, str] = field(default_factory=dict)
    #: UAV -> its heartbeat count when first seen disarmed / out of GUIDED
    _off_since: dict[int, int] = field(default_factory=dict)

    def retire(self, i: int, why: str) -> None:
        """UAV ``i`` is out of the mission for good (a resumed daemon sent it home,
        ``resume_takeback.py``): lost, with ``why``, at the next watch, and it never rejoins."""
        self.retired[i] = why

    def reason(self, i: int, v: VehicleState, now: float) -> str | None:
        """Why vehicle ``v`` (UAV ``i``) cannot take part in the mission now, or None."""
        if i in self.retired:
            return self.retired[i]
        closed = link_down(v)
        if closed is not None:
            return f"link {v.link.endpoint.spec}: {closed}"
        silent = v.silent_for(now)
        if silent > self.lost_after_s:
            return f"silent {silent:.1f} s"
        if not self.in_mission():
            return None
        off = None
        if not v.armed:
            off = "disarmed"
        elif not (autopilot := autopilot_for(v)).guided(v.custom_mode):
            off = f"left {autopilot.guided_name} (now {autopilot.mode_name(v.custom_mode)})"
        if off is None:
            self._off_since.pop(i, None)
            return None
        first = self._off_since.setdefault(i, v.heartbeats)
        return off if v.heartbeats - first >= 1 or v.lost else None

    def watch(self, step: int, now: float | None = None) -> None:
        """Mark who is lost and who rejoined at ``step`` (called at every pump)."""
        now = time.monotonic() if now is None else now
        back_within_s = min(1.0, self.lost_after_s / 2)
        vehicles = self.vehicles()
        if self.pauses is not None and vehicles:
            self.pauses.note(now, max(v.last_heard_s for v in vehicles))
        for i, v in enumerate(vehicles):
            paused = 0.0 if self.pauses is None else self.pauses.within(v.last_heard_s, now)
            why = self.reason(i, v, now - paused)
            if not v.lost and why is not None:
                v.lost = True
                self.reasons[i] = why
                reason = "silent" if why.startswith("silent") else why
                self.account.events.append(LinkEvent(step, i, "lost", now, reason))
                self.say(f"vehicle {v.key} lost at step {step} ({why}); the others go on")
            elif (
                v.lost
                and why is not None
                and self.reasons.get(i, "").startswith(GONE)
                and not why.startswith(GONE)
                and v.silent_for(now) < back_within_s
            ):
                self.reasons[i] = why
                self.account.events.append(LinkEvent(step, i, "back", now, why))
                self.say(
                    f"vehicle {v.key} is back at step {step} but {why}: it stays lost (a "
                    f"plane is not launched into the swarm in flight; it rejoins armed and in "
                    f"GUIDED)"
                )
            elif v.lost and why is None and v.silent_for(now) < back_within_s:
                v.lost = False
                self.reasons.pop(i, None)
                self.account.events.append(LinkEvent(step, i, "rejoined", now))
                self.say(f"vehicle {v.key} rejoined at step {step}")
