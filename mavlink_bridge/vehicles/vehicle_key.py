"""Which vehicle is which: a vehicle is known by (link, system id), and the scenario's UAVs map
onto those keys in one place (:class:`FleetMap`).

One MAVLink network addresses at most 255 systems, so a swarm of more vehicles flies on more
than one network, each numbering its vehicles from system id 1. The daemon's ``--connect``
endpoints form one network by default: system ids are unique across them, a vehicle may move
from one endpoint to another, and system id ``s`` is the scenario's UAV ``s - 1`` (SITL
instances and the simulator number them so). An endpoint written ``SPEC@FIRST``
(``udpin:127.0.0.1:14560@150``) is a network of its own whose system id ``s`` is UAV
``FIRST + s - 1`` (``swarmplan sim --first-uav FIRST``). Endpoints with the same FIRST share a
network.

A vehicle is named by its system id when there is one network (``3``: everything the daemon
writes is as it always was) and by ``LINK:SYSID`` when there are more (``2:3``: system id 3 of
the second network, networks numbered 1.. in the order of their first ``--connect``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

from planner.errors import UserError


class VehicleKey(NamedTuple):
    """A vehicle: its network (0 when there is only one; else 1, 2, ...) and its system id."""

    link: int
    system_id: int

    def __str__(self) -> str:
        return str(self.system_id) if self.link == 0 else f"{self.link}:{self.system_id}"

    def label(self) -> int | str:
        """How result.json names the vehicle: the system id (an int) on a single network, else
        ``"LINK:SYSID"``."""
        return self.system_id if self.link == 0 else str(self)


class FleetMapError(UserError):
    """The endpoints' first UAVs do not give every UAV flown one vehicle."""


def split_first_uav(spec: str) -> tuple[str, int]:
    """``"udpin:H:P@150"`` -> ``("udpin:H:P", 150)``; no ``@``: first UAV 0."""
    endpoint, at, first = spec.rpartition("@")
    if not at:
        return spec, 0
    if not first.isdigit():
        raise FleetMapError(
            f"--connect {spec!r}: after '@' comes the scenario's first UAV (0-based) whose "
            f"vehicles this endpoint serves, e.g. {endpoint}@150"
        )
    return endpoint, int(first)


@dataclass(frozen=True)
class FleetMap:
    """The scenario's UAVs flown (``fleet``) and the (link, system id) of each, given the first
    UAV of each endpoint (``first_uavs``, in ``--connect`` order)."""

    fleet: tuple[int, ...]
    first_uavs: tuple[int, ...] = (0,)

    def __post_init__(self) -> None:
        firsts = sorted(set(self.first_uavs))
        for uav in self.fleet:
            first = self._first_of(uav, firsts)
            if first is None:
                raise FleetMapError(
                    f"UAV {uav} is on no --connect endpoint: the first endpoint serves UAVs from "
                    f"{firsts[0]}; give one endpoint without '@' (or '@0')"
                )
            if uav - first + 1 > 255:
                raise FleetMapError(
                    f"UAV {uav} would be system id {uav - first + 1} of the network of "
                    f"--connect ...@{first}, beyond 255; put its vehicles on a network of their "
                    f"own (swarmplan sim --first-uav N, daemon --connect ...@N)"
                )

    @staticmethod
    def _first_of(uav: int, firsts: Sequence[int]) -> int | None:
        below = [f for f in firsts if f <= uav]
        return max(below) if below else None

    @property
    def networks(self) -> int:
        return len(set(self.first_uavs))

    def link_of_endpoint(self, endpoint_index: int) -> int:
        """The network of the ``endpoint_index``-th endpoint: 0 when there is one network, else
        1, 2, ... in order of first appearance."""
        if self.networks == 1:
            return 0
        order = list(dict.fromkeys(self.first_uavs))
        return order.index(self.first_uavs[endpoint_index]) + 1

    def key_of_uav(self, uav: int) -> VehicleKey:
        """The vehicle of the scenario's UAV ``uav``."""
        first = self._first_of(uav, sorted(set(self.first_uavs)))
        assert first is not None  # (checked in __post_init__)
        endpoint = self.first_uavs.index(first)
        return VehicleKey(self.link_of_endpoint(endpoint), uav - first + 1)

    def keys(self) -> list[VehicleKey]:
        """The vehicles flown, index = the daemon's UAV index."""
        return [self.key_of_uav(uav) for uav in self.fleet]
