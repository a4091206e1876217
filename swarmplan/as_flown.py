"""``swarmplan run --as-flown``: an offline run planned as the daemon plans the simulator's planes
(mavlink_bridge/mission/flown_planning.py)."""

from __future__ import annotations

from mavlink_bridge.mission.daemon import DaemonOptions, MissionDaemon
from mavlink_bridge.vehicles.airframe import airframe_from_params
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from planner.scenario import Scenario
from sim_gateway.parameters import default_specs


def simulator_planning_scenario(scenario: Scenario, steps: int | None = None) -> Scenario:
    """``scenario`` as a daemon with its default options plans it for ``steps`` decision steps,
    flying the airframes the simulator reports: each vehicle's parameter defaults, read as the
    daemon reads them at launch (``airframe_from_params``, ``MissionDaemon.use_airframes``)."""
    cfg = scenario.config
    daemon = MissionDaemon(scenario, DaemonOptions(connect=[], steps=steps or scenario.steps))
    airframes = []
    for sysid in range(1, scenario.uav_count + 1):
        vehicle = VehicleState(sysid, link=None)  # type: ignore[arg-type]  # never connected
        specs = default_specs(sysid, cfg.speed_mps, scenario.altitude_m)
        vehicle.params.update({spec.name: spec.default for spec in specs})
        airframes.append(airframe_from_params(vehicle, cfg))
    daemon.use_airframes(airframes)
    return daemon.planning_scenario()
