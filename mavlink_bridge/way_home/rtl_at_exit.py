"""The return home at every exit of a mission (the end, an error, Ctrl-C, SIGTERM): who gets RTL,
what is said about it, and when the planes count as home.

RTL goes to every **airborne** vehicle still **reachable** (its link up and heard within
``lost_after_s``), never to a grounded, disarmed one (an autopilot would take RTL on the ground
as a command to take off and fly home, or refuse it). Every other vehicle is listed with why not.
One unreachable at the way out is listened for while the flight home is watched, and sent home
the moment it is heard again (``heard_again``). After a completed mission the daemon listens on
until every plane circles its home (:class:`HomeWatch`), so the flight home is in the continuous
safety account.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

from mavlink_bridge.vehicles.discovery import _ids
from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_bridge.vehicles.vehicle_loss import link_down
from mavlink_bridge.vehicles.vehicle_state import VehicleState

#: the start of the reason a vehicle RTL could not reach is given (link down, or silent)
UNREACHABLE = "unreachable"


def rtl_recipients(
    vehicles: Iterable[VehicleState], lost_after_s: float, now_s: float | None = None
) -> tuple[list[VehicleState], dict[VehicleKey, str]]:
    """The vehicles RTL goes to (airborne, reachable), and for every other one (by system id)
    why not."""
    flying: list[VehicleState] = []
    skipped: dict[VehicleKey, str] = {}
    for v in sorted(vehicles, key=lambda v: v.key):
        closed = link_down(v)
        silent = v.silent_for(now_s)
        if closed is not None:
            skipped[v.key] = f"{UNREACHABLE}: {closed}"
        elif silent > lost_after_s:
            skipped[v.key] = f"{UNREACHABLE}: silent {silent:.0f} s"
        elif not v.airborne:
            skipped[v.key] = "on the ground, disarmed" if not v.armed else "on the ground"
        else:
            flying.append(v)
    return flying, skipped


def heard_again(waiting: Iterable[VehicleState], lost_after_s: float) -> list[VehicleState]:
    """Of ``waiting`` (vehicles RTL could not reach at the way out), those now airborne and
    reachable again: a GCS outage, a radio fade or a starved machine at the mission's end must
    not leave a plane circling its last target once it can be told to come home."""
    return rtl_recipients(waiting, lost_after_s)[0]


def rtl_line(
    sent: list[VehicleKey], accepted: list[VehicleKey], skipped: dict[VehicleKey, str]
) -> str:
    """What the daemon says of its RTL: to whom, who accepted, and who not and why."""
    if sent:
        line = f"RTL sent to vehicle{'s' if len(sent) > 1 else ''} {_ids(sent)}"
        if accepted != sent:
            line += f" (accepted by {_ids(accepted) or 'none'})"
    else:
        line = "RTL sent to no vehicle (none airborne and reachable)"
    if skipped:
        line += "; not to " + ", ".join(f"{k} ({why})" for k, why in skipped.items())
    return line


def away_km(v: VehicleState) -> float:
    """Distance of ``v`` from its home (flat earth: ample within a mission area)."""
    assert v.home is not None
    north = math.radians(v.lat_deg - v.home[0]) * 6371.0
    east = math.radians(v.lon_deg - v.home[1]) * 6371.0 * math.cos(math.radians(v.lat_deg))
    return math.hypot(north, east)


@dataclass
class HomeWatch:
    """Are the planes home? A plane is home once it has stayed within ``near_km`` (its loiter
    radius and half a kilometre) of its home for a whole circle of its own clock
    (``time_boot_ms``); a lost or disarmed plane is not waited for."""

    vehicles: list[VehicleState]  # those heard, with a home
    near_km: float
    speed_mps: float
    since_ms: dict[VehicleKey, int] = field(
        default_factory=dict
    )  # vehicle -> first clock near home

    @property
    def circle_ms(self) -> float:
        """One circle at ``speed_mps`` around home, of radius ``near_km`` less the half km."""
        return 2e3 * math.pi * (self.near_km - 0.5) * 1e3 / self.speed_mps

    def limit_s(self, rtl_watch_s: float | None) -> float:
        """How long to wait (vehicle seconds): ``rtl_watch_s``, by default the farthest plane's
        flight home, a circle and two minutes."""
        if rtl_watch_s is not None:
            return rtl_watch_s
        farthest_km = max((away_km(v) for v in self.vehicles), default=0.0)
        return farthest_km * 1e3 / self.speed_mps + self.circle_ms / 1e3 + 120.0

    def home(self) -> bool:
        for v in self.vehicles:
            if away_km(v) > self.near_km:
                self.since_ms.pop(v.key, None)
            else:
                self.since_ms.setdefault(v.key, v.time_boot_ms)
        return all(v.lost or not v.armed or self.circled(v) for v in self.vehicles)

    def circled(self, v: VehicleState) -> bool:
        """Has ``v`` stayed near its home for a whole circle of its clock?"""
        since = self.since_ms.get(v.key)
        return since is not None and v.time_boot_ms - since >= self.circle_ms
