"""When a decision step runs: one small interface, one implementation per source of time.

* :class:`LockstepPacing`: the daemon is the clock of a ``swarmplan sim --lockstep``: it grants
  one decision period and waits until every vehicle still heard holds at its end (its look of that
  instant has then arrived). Simulated time waits for the daemon: never late, no deadline.
* :class:`LookPacing`: the vehicles' cameras report one sensor look per decision period of
  their own clock; a step runs when every active vehicle's new look is in, or, for stragglers,
  0.4 x the measured step interval after the first one.
* :class:`VehicleClockPacing`: vehicles that send no looks (ArduPlane SITL or hardware without
  a payload simulator) but report their own clock (``time_boot_ms`` of GLOBAL_POSITION_INT and
  SYSTEM_TIME): a decision instant every ``step_s`` of each vehicle's clock, whatever the wall
  clock does (a speedup that is not the one the daemon was told, a loaded machine).
* :class:`WallClockPacing`: vehicles that report no time at all: one step per
  ``step_s / time_scale`` wall seconds, on a schedule; late against that schedule.

The last two hand over to :class:`LookPacing` as soon as a look arrives.

Every pacing answers the same three questions (:class:`Pacing`): wait for the next decision
instant (and return the looks of it), by when must this step's commands be out (``deadline``),
and how late is this step (``lateness``: measured once, here, as a :class:`Lateness`; a late
step is counted in ``late_steps`` and the first one said). A behaviour such as "hold when
late" (``keeping_up.HoldWhenLate``) reads that measure rather than measuring its own.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from mavlink_bridge.mission.lockstep_clock import LockstepClock
from mavlink_bridge.results.mission_result import MissionAccount
from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_bridge.vehicles.vehicle_state import Look, VehicleState

#: paced time: share of a decision period the daemon may spend getting a step's commands out
STEP_DEADLINE_SHARE = 0.6


@dataclass
class DecisionInstant:
    """What waiting for a decision instant produced."""

    step: int
    looks: dict[int, Look]  # UAV index -> its newest look (the ones new since the last step)
    deadline: float | None = None  # monotonic instant by which the commands must be out
    source: str = ""  # the pacing that produced it


@dataclass(frozen=True)
class Lateness:
    """How late a step's commands go out, in the vehicles' seconds: how far they had flown
    past the step's decision instant (``behind_s``), and the time since the previous decision
    instant (``gap_s``; None: the first one, or the first on another time base)."""

    step_s: float
    behind_s: float = 0.0
    gap_s: float | None = None

    @property
    def stalled(self) -> bool:
        """A whole decision instant passed without a decision (more than 1.5 periods)."""
        return self.gap_s is not None and self.gap_s > 1.5 * self.step_s

    @property
    def late(self) -> bool:
        """Planned from positions long gone (more than half a period behind), or stalled."""
        return self.behind_s > 0.5 * self.step_s or self.stalled

    @property
    def seconds(self) -> float:
        """The lateness in one number: behind, or the gap beyond one period (0: on time)."""
        stall = 0.0 if self.gap_s is None else self.gap_s - self.step_s
        return max(0.0, self.behind_s, stall)


@dataclass
class PacingContext:
    """What every pacing reads: the link, the expected vehicles (index = UAV), the loss watch
    run at every pump, the decision period and the vehicles' clock speed, and where lateness
    goes."""

    link: SwarmLink
    vehicles: Callable[[], list[VehicleState]]
    watch: Callable[[int], None]  # loss / return detection, called with the step at every pump
    step_s: float
    time_scale: float
    lost_after_s: float
    account: MissionAccount
    say: Callable[[str], None] = lambda text: None
    #: paced time: wall seconds between decision instants, as measured (median of the last 20)
    gaps: list[float] = field(default_factory=list)
    last_step_wall: float = 0.0
    decision_instant_ms: int | None = None

    @property
    def period_wall_s(self) -> float:
        """One decision period of the vehicles' clock, in wall seconds."""
        return self.step_s / max(self.time_scale, 1e-6)

    def gap_s(self) -> float:
        if self.gaps:
            return statistics.median(self.gaps[-20:])
        return self.period_wall_s

    def measure_gap(self) -> None:
        now = time.monotonic()
        if self.last_step_wall:
            self.gaps.append(now - self.last_step_wall)
        self.last_step_wall = now

    def new_looks(self, consumed: list[int]) -> dict[int, Look]:
        """The newest look of every vehicle still heard that sent one since ``consumed``."""
        return {
            i: v.looks[v.latest_look]
            for i, v in enumerate(self.vehicles())
            if v.latest_look > consumed[i] and not v.lost
        }

    def any_looks(self) -> bool:
        return any(v.latest_look >= 0 for v in self.vehicles())


def consume(fresh: dict[int, Look], consumed: list[int]) -> dict[int, Look]:
    """Mark ``fresh`` looks as used by a step."""
    for i, look in fresh.items():
        consumed[i] = look.index
    return fresh


class Pacing(Protocol):
    """One source of decision instants."""

    name: str

    def wait(self, step: int, consumed: list[int]) -> DecisionInstant | None:
        """Pump until the decision instant of ``step``; its looks (``consumed`` updated). None:
        this source does not apply any more (hand over to the next choice)."""

    def lateness(self, instant: DecisionInstant) -> Lateness:
        """Called as the step's commands go out: how far is the daemon behind the vehicles'
        clock? A late step is counted and said (the first time)."""


class LockstepPacing:
    """Grant one decision period of simulated time per step
    (``mavlink_bridge.mission.lockstep_clock``)."""

    name = "lockstep"

    def __init__(self, ctx: PacingContext, clock: LockstepClock) -> None:
        self.ctx = ctx
        self.clock = clock

    def wait(self, step: int, consumed: list[int]) -> DecisionInstant:
        self.clock.advance(self.ctx.vehicles(), on_pump=lambda: self.ctx.watch(step))
        return DecisionInstant(
            step, consume(self.ctx.new_looks(consumed), consumed), None, self.name
        )

    def lateness(self, instant: DecisionInstant) -> Lateness:
        return Lateness(self.ctx.step_s)  # simulated time waits for the daemon


class LookPacing:
    """Steps on the vehicles' sensor looks (one per decision period of their clock)."""

    name = "looks"

    def __init__(self, ctx: PacingContext) -> None:
        self.ctx = ctx

    def wait(self, step: int, consumed: list[int]) -> DecisionInstant:
        ctx = self.ctx
        start = time.monotonic()
        first_fresh: float | None = None
        gap = ctx.gap_s()
        limit = max(gap * 3, ctx.lost_after_s + 0.5)
        while True:
            ctx.link.pump(0.003)
            ctx.watch(step)
            now = time.monotonic()
            fresh = ctx.new_looks(consumed)
            vehicles = ctx.vehicles()
            waiting = [i for i, v in enumerate(vehicles) if i not in fresh and not v.lost]
            if fresh and first_fresh is None:
                first_fresh = now
            if fresh and not waiting:
                break
            if first_fresh is not None and now - first_fresh > max(0.05, 0.4 * gap):
                break  # stragglers miss this step's look
            if now - start > limit:
                break
        ctx.measure_gap()
        looks = consume(fresh, consumed)
        return DecisionInstant(step, looks, self.deadline(), self.name)

    def deadline(self) -> float:
        """60 % of a decision period (wall seconds at ``time_scale``) from now."""
        return time.monotonic() + STEP_DEADLINE_SHARE * self.ctx.period_wall_s

    def lateness(self, instant: DecisionInstant) -> Lateness:
        """A step is late when its commands go out more than half a decision period (of the
        vehicles' clock) after its decision instant (the newest look), so its targets were
        planned from positions long gone, or when a whole decision instant passed without a
        decision (the decision instants of this step and the last more than 1.5 periods apart:
        the daemon stalled, and the planes flew two legs on one command)."""
        looks = instant.looks
        if not looks:
            return Lateness(self.ctx.step_s)
        vehicles = self.ctx.vehicles()
        instant_ms = max(look.time_boot_ms for look in looks.values())
        behind_ms = max(vehicles[i].time_boot_ms - looks[i].time_boot_ms for i in looks)
        return note_late(self.ctx, instant.step, instant_ms, behind_ms)


class WallClockPacing:
    """Vehicles that report no time at all: a decision instant every ``step_s / time_scale``
    wall seconds from the start (a schedule, so a step's own computation does not stretch the
    next period). Lateness is judged on that schedule, as the vehicles' clock would be at the
    told speed: commands out more than half a period after their instant, or an instant skipped
    (the daemon stalled), count in ``late_steps``. Hands over (returns None) when a look
    arrives."""

    name = "wall clock"

    def __init__(self, ctx: PacingContext) -> None:
        self.ctx = ctx
        self.start_s = time.monotonic()  # step 0 is now
        self.last_s = self.start_s  # the last decision instant (monotonic)
        self.due_s = self.start_s  # this step's instant

    def resume(self, last_instant_s: float) -> None:
        """Take over from another pacing whose last decision instant was ``last_instant_s``."""
        self.last_s = self.due_s = last_instant_s

    def wait(self, step: int, consumed: list[int]) -> DecisionInstant | None:
        ctx = self.ctx
        self.due_s = self.last_s + ctx.period_wall_s
        while True:
            ctx.link.pump(0.003)
            ctx.watch(step)
            if ctx.new_looks(consumed):
                return None  # the cameras speak: pace by their looks
            if time.monotonic() >= self.due_s:
                break
        ctx.measure_gap()
        self.last_s = self.due_s
        return DecisionInstant(
            step, {}, time.monotonic() + STEP_DEADLINE_SHARE * ctx.period_wall_s, self.name
        )

    def lateness(self, instant: DecisionInstant) -> Lateness:
        """Late when the commands go out more than half a period after the instant, or an
        instant was skipped; whole periods passed are skipped (the schedule keeps its phase)."""
        ctx = self.ctx
        period = ctx.period_wall_s
        behind_s = time.monotonic() - self.due_s
        if behind_s >= period:
            self.last_s += (behind_s // period) * period
        scale_ms = 1e3 * max(ctx.time_scale, 1e-6)  # vehicle ms per wall s, as told
        instant_ms = round((self.due_s - self.start_s) * scale_ms)
        return note_late(ctx, instant.step, instant_ms, round(behind_s * scale_ms))


class VehicleClockPacing:
    """A decision instant every ``step_s`` of each vehicle's own clock (``VehicleState.clock_ms``).

    Each active vehicle's next instant is its last one plus a step (the first: its clock when
    the loop started; a vehicle that rejoins: its clock then). The step runs when every active
    vehicle's clock has reached its instant, or, for stragglers, 0.4 of a measured step interval
    after the first one did. A step whose vehicles already flew more than half a step past
    their instant as its commands go out is late, and so is one that skipped an instant (the
    daemon stalled): both counted in ``late_steps``. Hands over (returns None) when a look
    arrives."""

    name = "vehicle clock"

    def __init__(self, ctx: PacingContext) -> None:
        self.ctx = ctx
        self.last_ms: dict[int, int] = {}  # UAV -> its clock at the last decision instant
        self.due_ms: dict[int, int] = {}  # UAV -> this step's instant on its clock
        self.rates: list[float] = []  # measured vehicle-clock seconds per wall second
        self._mark: tuple[float, int] | None = None

    def start(self, vehicles: list[VehicleState]) -> None:
        """Step 0 is now, on every vehicle's clock."""
        self.last_ms = {i: v.clock_ms for i, v in enumerate(vehicles) if v.clock_ms > 0}

    @property
    def rate(self) -> float:
        """The vehicles' clock speed (vehicle s per wall s): measured, else ``time_scale``."""
        if self.rates:
            return statistics.median(self.rates[-10:])
        return self.ctx.time_scale

    def wait(self, step: int, consumed: list[int]) -> DecisionInstant | None:
        ctx = self.ctx
        step_ms = round(1e3 * ctx.step_s)
        start = time.monotonic()
        first_due: float | None = None
        limit = max(3 * ctx.step_s / max(self.rate, 1e-6), ctx.lost_after_s + 0.5)
        while True:
            ctx.link.pump(0.003)
            ctx.watch(step)
            if ctx.new_looks(consumed):
                return None  # the cameras speak: pace by their looks
            now = time.monotonic()
            active = {i: v for i, v in enumerate(ctx.vehicles()) if not v.lost}
            for i, v in active.items():
                if i not in self.last_ms and v.clock_ms > 0:
                    self.last_ms[i] = v.clock_ms - step_ms  # (re)joined: its instant is now
            due = {i: self.last_ms[i] + step_ms for i in active if i in self.last_ms}
            reached = [i for i in due if active[i].clock_ms >= due[i]]
            if reached and first_due is None:
                first_due = now
            if due and len(reached) == len(due):
                break
            if first_due is not None and now - first_due > max(0.05, 0.4 * ctx.gap_s()):
                break  # stragglers: their positions are a little older than the instant
            if now - start > limit:
                break
        ctx.measure_gap()
        self.due_ms = due
        for i in due:
            self.last_ms[i] = due[i]
        for i in [i for i in self.last_ms if i not in active]:
            del self.last_ms[i]  # lost: it starts afresh when it rejoins
        self._measure_rate(active)
        deadline = time.monotonic() + STEP_DEADLINE_SHARE * ctx.step_s / max(self.rate, 1e-6)
        return DecisionInstant(step, {}, deadline, self.name)

    def _measure_rate(self, active: dict[int, VehicleState]) -> None:
        clocks = [v.clock_ms for v in active.values() if v.clock_ms > 0]
        if not clocks:
            return
        now, clock = time.monotonic(), max(clocks)
        if self._mark is not None and now > self._mark[0] and clock > self._mark[1]:
            self.rates.append((clock - self._mark[1]) / 1e3 / (now - self._mark[0]))
        self._mark = (now, clock)

    def lateness(self, instant: DecisionInstant) -> Lateness:
        """Late when the vehicles flew more than half a step past their instant before the
        commands went out, or when an instant was skipped; a skipped instant moves the vehicle's
        next instant on to the step it is in (the schedule keeps the vehicle's clock)."""
        if not self.due_ms:
            return Lateness(self.ctx.step_s)
        step_ms = round(1e3 * self.ctx.step_s)
        vehicles = self.ctx.vehicles()
        behind = {i: vehicles[i].clock_ms - due for i, due in self.due_ms.items()}
        for i, ms in behind.items():
            if ms >= step_ms and i in self.last_ms:  # whole instants passed: skip them
                self.last_ms[i] += (ms // step_ms) * step_ms
        return note_late(self.ctx, instant.step, max(self.due_ms.values()), max(behind.values()))


def note_late(ctx: PacingContext, step: int, instant_ms: int, behind_ms: int) -> Lateness:
    """The lateness of a step whose decision instant was ``instant_ms`` and whose vehicles were
    ``behind_ms`` past it; a late step is counted (``late_steps``) and the first one said with
    what to do about it."""
    previous_ms, ctx.decision_instant_ms = ctx.decision_instant_ms, instant_ms
    gap_s = None if previous_ms is None else (instant_ms - previous_ms) / 1e3
    lateness = Lateness(ctx.step_s, behind_ms / 1e3, gap_s)
    if not lateness.late:
        return lateness
    ctx.account.late_steps += 1
    if ctx.account.late_steps == 1:
        what = (
            f"{gap_s:.0f} s passed between two decisions"
            if lateness.stalled and gap_s is not None
            else f"they had flown {behind_ms / 1e3:.1f} s past the decision instant as its "
            "commands went out"
        )
        ctx.say(
            f"warning: the daemon is behind the vehicles' clock at step {step}: {what} (a "
            f"step is {ctx.step_s:g} s); lower the vehicles' speedup (--time-scale "
            f"{ctx.time_scale:g}) or use lockstep"
        )
    return lateness


class PacingChoice:
    """Picks the pacing of each step: lockstep when granted, else the looks once any vehicle
    has sent one, else the vehicles' own clock when they report it, else the wall clock (the
    last two hand over to the looks when they start)."""

    def __init__(self, ctx: PacingContext, clock: LockstepClock | None) -> None:
        self.ctx = ctx
        self.lockstep = None if clock is None else LockstepPacing(ctx, clock)
        self.looks = LookPacing(ctx)
        self.vehicle_clock = VehicleClockPacing(ctx)
        self.wall = WallClockPacing(ctx)
        self.current: Pacing = self.lockstep or self.wall
        self.vehicle_clock.start(ctx.vehicles())

    def choose(self) -> Pacing:
        if self.lockstep is not None:
            return self.lockstep
        if self.ctx.any_looks():
            return self.looks
        if any(v.clock_ms > 0 for v in self.ctx.vehicles() if not v.lost):
            return self.vehicle_clock
        return self.wall

    def wait(self, step: int, consumed: list[int]) -> DecisionInstant:
        while True:
            chosen = self.choose()
            if (chosen is self.wall) != (self.current is self.wall):
                self.ctx.decision_instant_ms = None  # another time base: no stall across it
                if chosen is self.wall:
                    self.wall.resume(self.ctx.last_step_wall or time.monotonic())
            self.current = chosen
            instant = self.current.wait(step, consumed)
            if instant is not None:
                return instant
