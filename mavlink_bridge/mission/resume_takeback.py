"""Taking the planes back after a restart (``swarmplan daemon --checkpoint F --resume``).

While the daemon was down its planes flew on their own: their GCS failsafe (after
FS_LONG_TIMEOUT without the daemon's heartbeat; ``gcs_failsafe.py``) kept them circling their
last guided target, a pilot may have switched modes (RTL, LOITER, CIRCLE, AUTO), a battery
(range) failsafe may have sent them home, a fence breach may have switched them to RTL. A plane
in any failsafe reports MAV_STATE_CRITICAL (ArduPlane: while a failsafe is on; its GCS
failsafe ends with the ground station's first heartbeat, the battery failsafe stays until
disarmed; the simulator does the same, sim_gateway/vehicle.py). A fresh launch waits for
STANDBY or ACTIVE (``discovery.wait_until_ready``); a resumed daemon does not wait for a plane
that is flying, whatever it reports.

Every plane that is armed and above the take-off height (:func:`flying`, the launch's own test
of a plane already in the air) is taken back whatever its system status and mode, and judged
from where it is (:meth:`TakeBackJudge.judge`). It is **sent home** when

* it is inside a threat zone, or its fence reports a breach;
* it is outside the mission area by more than its loiter reach;
* its range is spent: what it has flown (:class:`RangeAccount`: the checkpoint's account plus
  the outage flown at its speed, or what its battery says is used of L_max, whichever is more)
  plus the safe way home (``safe_return.HomeRoutes.way_length_km``) plus the planner's reserve
  for turns (``return_reserve_km``) exceeds L_max: the planner's range-with-return constraint
  (C_r, ``planner/feasibility.py``) with nothing left to move with.

Any other plane **continues**: the launch's take-off phase switches it back to GUIDED, and from
the next step it is the planner's again, with the outage's flight added to its range account
(:func:`account_outage`) so that the planner brings it home in time. A plane sent home flies the
daemon's safe flight home (``flight_home.homeward_commands``: RTL where the line home is clear,
else guided around the threats, re-judged at every step by ``flight_home.guide_sent_home``) and
is lost to the planner for the rest of the mission (``vehicle_loss.LossWatch.retire``). One line
per plane says which and why; result.json keeps them (``resume_decisions``).

A plane on the ground (disarmed, or armed below the take-off height) is readied, armed and
launched as at a fresh launch; a plane not heard at all stops the launch at discovery
(``--timeout``), as it does at a fresh launch.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mavlink_bridge.vehicles.autopilot_adapter import autopilot_for
from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_bridge.way_home.around_threats import HomeRoutes
from mavlink_wire.protocol import enum_name

if TYPE_CHECKING:
    from mavlink_bridge.mission.context import MissionContext
    from mavlink_bridge.mission.loop_state import LoopState
    from mavlink_bridge.results.checkpoint import Checkpoint
    from mavlink_bridge.vehicles.guided_commands import Command
    from mavlink_bridge.vehicles.vehicle_loss import LossWatch
    from mavlink_bridge.way_home.flight_home import FlightHomePhase

CONTINUE, HOME, LAUNCH = "continue", "home", "launch"
_VERBS = {
    CONTINUE: "continues the mission",
    HOME: "is sent home",
    LAUNCH: "is launched again",
}


def flying(v: VehicleState, climb_m: float) -> bool:
    """Armed and at least ``climb_m`` above home: a plane already in the air, which the
    launch sends straight to GUIDED (no TAKEOFF) and a resumed daemon takes back."""
    return v.armed and v.has_position and v.relative_alt_m >= climb_m


@dataclass(frozen=True)
class RangeAccount:
    """What a plane has flown by the resume, as well as the daemon knows it."""

    at_checkpoint_km: float  # the envelope's account at the checkpoint's step
    outage_km: float  # the outage at the plane's speed (its clock: wall time x time scale)
    battery_used_km: float | None  # L_max x the share of its battery used (None: not reported)

    @property
    def flown_km(self) -> float:
        estimate = self.at_checkpoint_km + self.outage_km
        return max(estimate, self.battery_used_km or 0.0)

    def describe(self) -> str:
        text = f"{self.at_checkpoint_km:.0f} km by the checkpoint + ~{self.outage_km:.0f} km since"
        if self.battery_used_km is not None:
            text += f"; battery: {self.battery_used_km:.0f} km used"
        return text


@dataclass(frozen=True)
class TakeBack:
    """The resumed daemon's decision for one plane, and why."""

    key: VehicleKey
    decision: str  # CONTINUE, HOME or LAUNCH
    why: str
    mode: str
    status: str
    flown_km: float | None = None
    way_home_km: float | None = None
    #: flown during the outage beyond the straight chord the first step will count
    outage_extra_km: float = 0.0

    def line(self) -> str:
        return (
            f"resume: vehicle {self.key} ({self.mode}, {self.status}) "
            f"{_VERBS[self.decision]}: {self.why}"
        )

    def row(self) -> dict[str, Any]:
        """Its entry in result.json (``resume_decisions``)."""

        def km(x: float | None) -> float | None:
            return None if x is None or not math.isfinite(x) else round(x, 2)

        return {
            "vehicle": self.key.label(),
            "decision": self.decision,
            "why": self.why,
            "mode": self.mode,
            "status": self.status,
            "flown_km": km(self.flown_km),
            "way_home_km": km(self.way_home_km),
        }


@dataclass(frozen=True)
class TakeBackJudge:
    """What a flying plane is judged against (see the module docstring)."""

    routes: HomeRoutes  # the daemon's safe ways home (threats, margin, plane model)
    area_km: tuple[float, float]
    edge_km: float  # how far outside the area a plane may be (its loiter reach)
    max_range_km: float  # L_max
    reserve_km: float  # the planner's reserve for turns on the way home

    def judge(
        self,
        v: VehicleState,
        xy_km: np.ndarray,
        home_km: np.ndarray,
        flown: RangeAccount,
    ) -> TakeBack:
        """Continue or home, and why, for plane ``v`` at ``xy_km`` (mission frame)."""
        mode, status = autopilot_for(v).mode_name(v.custom_mode), state_name(v.system_status)
        flown_km = flown.flown_km

        def verdict(decision: str, why: str, way: float | None = None) -> TakeBack:
            return TakeBack(v.key, decision, why, mode, status, flown_km, way)

        inside = self.threat_inside(xy_km)
        if inside is not None:
            return verdict(HOME, f"it is inside {inside}; the safe way home takes it out")
        if v.fence_breached:
            return verdict(HOME, "its fence reports a breach (inside a threat zone)")
        x, y = float(xy_km[0]), float(xy_km[1])
        width, height = self.area_km
        out = max(-x, x - width, -y, y - height)
        if out > self.edge_km:
            return verdict(
                HOME, f"it is {out:.1f} km outside the {width:g} x {height:g} km mission area"
            )
        way = self.routes.way_length_km(xy_km, home_km)
        if not math.isfinite(way):
            return verdict(HOME, "no way home clear of the threats is known from where it is")
        clear = float(self.routes.point_clearance(np.asarray(xy_km, float)[None])[0])
        where = "no threats" if not math.isfinite(clear) else f"{clear:.1f} km clear of the threats"
        if not math.isfinite(self.max_range_km):
            return verdict(CONTINUE, f"{where}, no range limit", way)
        left = self.max_range_km - flown_km
        need = way + self.reserve_km
        if need > left:
            return verdict(
                HOME,
                f"range spent: flown ~{flown_km:.0f} of L_max {self.max_range_km:g} km "
                f"({flown.describe()}), {max(left, 0.0):.0f} km left for a "
                f"{way:.1f} km way home + {self.reserve_km:g} km reserve",
                way,
            )
        return verdict(
            CONTINUE,
            f"{where}; range left ~{left:.0f} km of L_max {self.max_range_km:g} "
            f"(flown: {flown.describe()}), way home {way:.1f} km + {self.reserve_km:g} km "
            "reserve",
            way,
        )

    def threat_inside(self, xy_km: np.ndarray) -> str | None:
        """The threat zone ``xy_km`` is in, in words (None: in none)."""
        centres, radii = self.routes.threat_xy_km, self.routes.threat_radius_km
        if len(radii) == 0:
            return None
        depth = radii - np.hypot(*(centres - np.asarray(xy_km, float)).T)
        k = int(np.argmax(depth))
        if depth[k] <= 0:
            return None
        return (
            f"threats[{k}] (centre ({centres[k][0]:g}, {centres[k][1]:g}) km, radius "
            f"{radii[k]:g} km; {depth[k]:.1f} km deep)"
        )


def state_name(system_status: int) -> str:
    """``CRITICAL`` for MAV_STATE_CRITICAL."""
    return enum_name("MAV_STATE", system_status).removeprefix("MAV_STATE_")


def outage_s(checkpoint_path: Path, time_scale: float, now_unix_s: float | None = None) -> float:
    """Seconds of the vehicles' clock since the checkpoint was written (its file's time; the
    restarted daemon writes none before its first step), at ``time_scale``."""
    now = time.time() if now_unix_s is None else now_unix_s
    try:
        written = checkpoint_path.stat().st_mtime
    except OSError:
        return 0.0
    return max(0.0, now - written) * time_scale


def range_account(
    v: VehicleState,
    at_checkpoint_km: float,
    outage_s: float,
    cruise_mps: float,
    max_range_km: float,
) -> RangeAccount:
    """What ``v`` has flown: the checkpoint's account plus the outage at its speed (at least
    cruise: a plane circling its last target flies the last airspeed asked, up to the leg
    timing's fastest), and what its battery says is used of L_max, where it reports one."""
    speed = max(cruise_mps, v.speed_mps)
    battery = None
    if 0 <= v.battery_pct <= 100 and math.isfinite(max_range_km):
        battery = max_range_km * (100 - v.battery_pct) / 100.0
    return RangeAccount(float(at_checkpoint_km), outage_s * speed / 1000.0, battery)


def account_outage(
    state: LoopState, decisions: list[TakeBack], index_of: Callable[[VehicleKey], int]
) -> None:
    """Add what each plane that continues flew during the outage (beyond the straight chord
    its first step counts) to the planner's L_past and the envelope's account, so that both
    bring it home within L_max."""
    for t in decisions:
        i = index_of(t.key)
        if t.decision == CONTINUE and t.outage_extra_km > 0:
            state.flown_km[i] += t.outage_extra_km
            distance = getattr(state.planner, "distance_km", None)
            if distance is not None:
                distance[i] += t.outage_extra_km


def judge_fleet(
    ctx: MissionContext, routes: HomeRoutes, resume_from: Checkpoint | None, climb_m: float
) -> list[TakeBack]:
    """Every expected plane's decision at the resume from ``resume_from`` (module docstring):
    a plane flying is judged from where it is (``routes``: the safe ways home), one on the
    ground is launched again."""
    assert resume_from is not None and ctx.options.checkpoint_path is not None
    loop = resume_from.loop
    cfg = ctx.scenario.config
    judge = TakeBackJudge(
        routes,
        cfg.area_km,
        float(ctx.plane.loiter_reach_km()),
        cfg.max_range_km,
        cfg.return_reserve_km,
    )
    seconds = outage_s(ctx.options.checkpoint_path, ctx.time_scale)
    decisions = []
    for i, v in enumerate(ctx.vehicles()):
        mode, status = autopilot_for(v).mode_name(v.custom_mode), state_name(v.system_status)
        if not flying(v, climb_m):
            where = (
                f"armed {v.relative_alt_m:.0f} m above home, below the take-off height "
                f"{climb_m:g} m"
                if v.armed
                else "disarmed"
            )
            why = f"{where}: readied, armed and taken off as at a fresh launch"
            decisions.append(TakeBack(v.key, LAUNCH, why, mode, status))
            continue
        xy = ctx.local_km(v.lat_deg, v.lon_deg)
        home = (
            ctx.local_km(v.home[0], v.home[1])
            if v.home is not None
            else np.asarray(loop["home_km"][i], float)
        )
        flown = range_account(
            v, float(loop["flown_km"][i]), seconds, ctx.plane.speed_mps, cfg.max_range_km
        )
        verdict = judge.judge(v, xy, home, flown)
        chord = float(np.hypot(*(xy - np.asarray(loop["positions"][i], float))))
        extra = max(0.0, flown.flown_km - flown.at_checkpoint_km - chord)
        decisions.append(replace(verdict, outage_extra_km=extra))
    return decisions


def send_home(
    ctx: MissionContext, flight_home: FlightHomePhase, loss: LossWatch, decisions: list[TakeBack]
) -> None:
    """The planes judged HOME: out of the mission for good (lost to the planner, with why)
    and on the daemon's safe flight home (RTL where the line home is clear, else guided
    around the threats; re-judged at every step by ``flight_home.guide_sent_home``)."""
    home = {t.key: t.why for t in decisions if t.decision == HOME}
    if home:
        send_planes_home(ctx, flight_home, loss, home, "sent home at the resume")


def send_planes_home(
    ctx: MissionContext,
    flight_home: FlightHomePhase,
    loss: LossWatch,
    why: dict[VehicleKey, str],
    lost_reason: str,
) -> list[Command]:
    """Planes (vehicle key -> why) out of the mission for good: lost to the planner with
    ``lost_reason`` (``LossWatch.retire``) and on the daemon's safe flight home (RTL where the
    line home is clear, else guided around the threats; re-judged at every decision step by
    ``flight_home.guide_sent_home``). A resumed daemon's planes judged HOME, and the planes an
    operator sends home (``operator_actions.py``). Returns the commands sent, answered."""
    by_id = {v.key: v for v in ctx.vehicles()}
    for key, reason in why.items():
        flight_home.send_home(key, reason)
        loss.retire(ctx.index_of(key), lost_reason)
    planes = [by_id[s] for s in why if s in by_id]
    sent = ctx.send(flight_home.homeward_commands(planes, announce=True))
    for c in sent:
        if not c.accepted:
            ctx.say(f"warning: {c.describe_failure()}")
    return sent
