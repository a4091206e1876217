"""Waiting for the swarm: every expected vehicle heard, then every one past its initialisation.

The vehicles are waited for by their (link, system id) keys (``vehicle_key.FleetMap``: on one
network vehicle ``i`` of the scenario, 0-based, is system id ``i + 1``, the way SITL instances and
the simulator number them), and named in what is said as ``vehicle_key.VehicleKey`` says.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_wire.protocol import enum_name
from planner.errors import UserError


class DiscoveryError(UserError):
    """Expected vehicles never appeared, or never finished initialising."""


def _ids(ids: list[VehicleKey]) -> str:
    return ", ".join(str(i) for i in ids)


def wait_for_vehicles(
    link: SwarmLink,
    expected_ids: list[VehicleKey],
    timeout_s: float,
    progress: Callable[[str], None] | None = None,
) -> None:
    """Pump until a heartbeat of every expected system id has been heard.

    Raises DiscoveryError naming the missing system ids and the endpoints listened on."""
    start = time.monotonic()
    last_report = -1
    while True:
        missing = [i for i in expected_ids if i not in link.vehicles]
        if not missing:
            return
        elapsed = time.monotonic() - start
        if elapsed >= timeout_s:
            heard = sorted(link.vehicles)
            heard_text = f" (heard: {_ids(heard)})" if heard else " (heard no vehicle at all)"
            raise DiscoveryError(
                f"vehicle{'s' if len(missing) > 1 else ''} with system id {_ids(missing)} did not "
                f"appear within {timeout_s:g} s on {link.describe()}{heard_text}; start them, "
                f"check where they send to, or lower --expect"
            )
        if progress is not None and len(expected_ids) - len(missing) != last_report:
            last_report = len(expected_ids) - len(missing)
            progress(f"waiting for vehicles: {last_report}/{len(expected_ids)} heard")
        link.pump(min(0.1, timeout_s - elapsed))


def wait_until_ready(
    link: SwarmLink,
    system_ids: list[VehicleKey],
    timeout_s: float,
    wait: Callable[[Callable[[], bool], float], bool] | None = None,
) -> None:
    """Pump until every vehicle reports system_status STANDBY (or ACTIVE): an autopilot refuses
    uploads and arming while it initialises (ArduPilot: ~20 s for the EKF to get GPS).

    ``wait(done, timeout_s)`` replaces ``link.pump_until`` (the daemon's lockstep clock grants
    simulated time while it waits)."""

    def ready() -> bool:
        return all(link.vehicles[i].standby_or_active for i in system_ids)

    if not (wait or link.pump_until)(ready, timeout_s):
        waiting = [i for i in system_ids if not link.vehicles[i].standby_or_active]
        states = {enum_name("MAV_STATE", link.vehicles[i].system_status) for i in waiting}
        raise DiscoveryError(
            f"vehicle{'s' if len(waiting) > 1 else ''} {_ids(waiting)} still initialising "
            f"({', '.join(sorted(states))}) after {timeout_s:g} s; wait for GPS/EKF or raise "
            f"--ready-timeout"
        )
