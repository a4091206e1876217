"""The watch of the flight home after a completed mission: the daemon listens on (in lockstep:
grants time) until every plane circles its home (``rtl_at_exit.HomeWatch``), so that the flight
home is in the continuous safety account; meanwhile it re-judges the planes guided around the
threats or held for another's way home, and sends home every plane RTL could not reach at the
way out as soon as it is heard again (a GCS outage or a starved machine at the mission's end,
:func:`reach_late`).
"""

from __future__ import annotations

from mavlink_bridge.vehicles.autopilot_adapter import autopilot_for
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_bridge.way_home.flight_home import FlightHomePhase
from mavlink_bridge.way_home.rtl_at_exit import HomeWatch, heard_again


def watch_flight_home(phase: FlightHomePhase) -> None:
    """Listen on (in lockstep: grant time) until every vehicle still heard circles its home
    (``return_home.HomeWatch``), for the continuous account of the flight home
    (``rtl_watch_s``); a plane RTL could not reach at the way out is sent home as soon as
    it is heard again within the watch (:func:`reach_late`)."""
    flight = phase.state
    vehicles = [v for v in phase.ctx.vehicles() if not v.lost and v.home is not None]
    pending = [v for v in phase.ctx.vehicles() if v.key in flight.unreached]
    if not vehicles and not pending:
        return
    near_km = float(phase.ctx.plane.loiter_radius_km()) + 0.5
    slowest = min(flight.circles.speeds_mps.values(), default=phase.ctx.plane.speed_mps)
    watch = HomeWatch(vehicles, near_km, slowest)
    limit_s = watch.limit_s(phase.ctx.options.rtl_watch_s)
    if limit_s <= 0:
        return
    lost_after_s = phase.ctx.options.lost_after_s
    if pending:
        phase.ctx.say(
            f"listening for vehicle(s) {', '.join(str(v.key) for v in pending)} (unreachable) "
            f"for up to {limit_s:.0f} s of the flight home's watch, to send them home"
        )

    def event() -> bool:  # every plane home, or one unreached heard again
        back = bool(heard_again(pending, lost_after_s))
        return back or (not pending and watch.home())

    # planes flying a safe way home (around_threats.py) or holding for another's
    # (kept_apart.py) are re-judged once per decision period, and so are the planes waited
    # for; the time a plane holds is added to the watch (at most once more its length)
    period_s = phase.ctx.scenario.config.step_s
    waited_s = extra_s = 0.0
    while waited_s < limit_s + extra_s:
        left_s = limit_s + extra_s - waited_s
        guiding = bool(flight.homing or flight.holding or pending)
        chunk_s = min(period_s, left_s) if guiding else left_s
        phase.listen(event, chunk_s)
        waited_s += chunk_s
        if flight.holding:
            extra_s = min(limit_s, extra_s + chunk_s)
        vehicles += [v for v in reach_late(phase, pending, watch) if v not in vehicles]
        # (home judged afresh: a plane heard again has only now been sent home)
        if not (flight.homing or flight.holding or pending) and watch.home():
            return
        guided = flight.homing.keys() | flight.holding.keys()
        flying = [v for v in vehicles if not v.lost and v.key in guided]
        phase.slow_home_circles(phase.ctx.send(phase.homeward_commands(flying, announce=False)))
    still = [v for v in vehicles if not v.lost and v.key in flight.holding]
    if still:
        phase.ctx.say(
            "warning: the watch of the flight home ends with vehicle(s) "
            f"{', '.join(str(v.key) for v in still)} still holding: RTL sent"
        )
        for v in still:
            flight.holding.pop(v.key)
        phase.slow_home_circles(phase.ctx.send([autopilot_for(v).rtl_command(v) for v in still]))
    if pending:
        phase.ctx.say(
            "warning: the watch of the flight home ends with vehicle(s) "
            f"{', '.join(str(v.key) for v in pending)} not heard again in flight: no RTL "
            "reached them; they fly their autopilot's link-loss action"
        )
    # every plane that got its RTL during the watch (guided around a threat, held first or
    # heard again; the last maybe as the watch ended) says its return mode before the log closes
    later = (flight.detoured | flight.held) - set(flight.homing) | {v.key for v in still}
    later |= flight.reached_late
    phase.see_rtl([v for v in vehicles if not v.lost and v.key in later])


def reach_late(
    phase: FlightHomePhase, pending: list[VehicleState], watch: HomeWatch
) -> list[VehicleState]:
    """The planes of ``pending`` (RTL could not reach them at the way out) heard again,
    airborne: each sent home (RTL, or guided around the threats), said, no longer lost, and
    watched from now on; removed from ``pending``."""
    back = heard_again(pending, phase.ctx.options.lost_after_s)
    for v in back:
        pending.remove(v)
        v.lost = False
        if v.home is not None and v not in watch.vehicles:
            watch.vehicles.append(v)
        phase.state.reached_late.add(v.key)
        phase.ctx.say(f"vehicle {v.key} heard again after the mission's end: sent home")
    if back:
        sent = phase.ctx.send(phase.homeward_commands(back, announce=True))
        phase.slow_home_circles(sent)
    return back
