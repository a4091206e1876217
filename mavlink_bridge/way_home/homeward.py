"""One plane's next stretch home, as predicted: where it is at each instant from now.

A :class:`Homeward` is either a straight leg (from where the plane is to an aim, through a
detour point on the way, at a constant speed, then circling the aim) or the path the plane model
flies (``homeward_flights.py``): the turn onto the way, the overshoot and the circle. Once a
plane circles its aim, where on the circle it is stops being known (``PHASE_TRUSTED_S``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from mavlink_bridge.vehicles.vehicle_key import VehicleKey

#: how long the plane model's place on a loiter circle is trusted: beyond, a circling plane is
#: anywhere on its circle (its phase drifts with every late command and gust)
PHASE_TRUSTED_S = 20.0


@dataclass(frozen=True)
class Homeward:
    """One plane's next stretch home as predicted: straight to ``aim_km`` at ``speed_kmps``
    (through ``via_km`` first, when it detours), then circling it (straying ``circle_km`` from
    it); ``at_home``: the aim is its home. With ``path_km`` (RTL home from where the plane
    is, its course and speed known: :meth:`HomewardFlights.flights_home`) the flight is the
    plane model's (the turn onto the way, the overshoot, the circle), every ``path_dt_s``."""

    key: VehicleKey
    start_km: np.ndarray  # (2,)
    aim_km: np.ndarray  # (2,)
    speed_kmps: float
    circle_km: float
    at_home: bool
    via_km: np.ndarray | None = None  # (2,) a detour point flown through on the way
    path_km: np.ndarray | None = None  # (S + 1, 2) predicted positions from now
    path_dt_s: float = 2.0
    path_arrival_s: float = 0.0  # when the predicted path reaches its circle
    #: the same flight turning about the other way (``HomewardFlights.turns_about_rad``)
    alternatives: tuple[Homeward, ...] = ()

    @property
    def variants(self) -> tuple[Homeward, ...]:
        return (self, *self.alternatives)

    @property
    def length_km(self) -> float:
        if self.via_km is None:
            return float(np.hypot(*(self.aim_km - self.start_km)))
        return float(np.hypot(*(self.via_km - self.start_km))) + float(
            np.hypot(*(self.aim_km - self.via_km))
        )

    @property
    def predicted(self) -> bool:
        return self.path_km is not None

    @property
    def settled(self) -> bool:
        """Already on its circle around the aim (within its loiter radius and a fifth): it
        strays its radius from the aim, not the overshoot of a plane arriving there."""
        return self.via_km is None and self.length_km <= 0.6 * self.circle_km

    @property
    def stray_at_aim_km(self) -> float:
        """How far from its aim it strays once there: its loiter radius when settled, else a
        loiter diameter (``circle_km``: it passes the point before it turns onto its circle)."""
        return self.circle_km / 2 if self.settled else self.circle_km

    @property
    def arrival_s(self) -> float:
        if self.path_km is not None:
            return self.path_arrival_s
        return self.length_km / max(self.speed_kmps, 1e-6)

    @cached_property
    def extent_km(self) -> tuple[np.ndarray, np.ndarray]:
        """The corners (lowest x and y, highest x and y) of a box holding every place
        :meth:`positions` gives, at any instant, of this flight and its ``alternatives``: two
        flights whose boxes are far apart cannot come near each other, whenever they fly."""
        places = [self.aim_km[None]]
        for v in self.variants:
            if v.path_km is not None:
                places.append(v.path_km)
            places.append(np.stack([v.start_km, v.aim_km]))
            if v.via_km is not None:
                places.append(v.via_km[None])
        every = np.concatenate(places)
        return every.min(axis=0), every.max(axis=0)

    def circling(self, t_s: np.ndarray) -> np.ndarray:
        """At which instants a predicted flight counts as anywhere on its circle: once it is
        there and ``PHASE_TRUSTED_S`` from now (the model's place on the circle is trusted
        that long: a plane on its circle now is where it is, not anywhere on it)."""
        t = np.asarray(t_s, float)
        return (t >= self.path_arrival_s) & (t >= PHASE_TRUSTED_S)

    def positions(self, t_s: np.ndarray) -> np.ndarray:
        """(len(t_s), 2) where the plane is at each instant: at the aim once arrived (on a
        predicted path too: where on its circle a plane will be minutes ahead is not known, so
        the whole circle is its place, ``HomewardFlights._stray_km``)."""
        if self.path_km is not None:
            t = np.asarray(t_s, float)
            index = np.rint(t / self.path_dt_s).astype(int)
            out = self.path_km[np.clip(index, 0, len(self.path_km) - 1)]
            return np.where(self.circling(t)[:, None], self.aim_km[None], out)
        flown = np.clip(np.asarray(t_s, float) * self.speed_kmps, 0.0, self.length_km)
        corners = [self.start_km] + ([] if self.via_km is None else [self.via_km]) + [self.aim_km]
        out = np.repeat(self.start_km[None], len(flown), axis=0)
        done = 0.0
        for a, b in zip(corners[:-1], corners[1:], strict=True):
            length = float(np.hypot(*(b - a)))
            frac = np.clip((flown - done) / max(length, 1e-9), 0.0, 1.0)
            here = flown >= done
            out[here] = a[None] + frac[here, None] * (b - a)[None]
            done += length
        return out
