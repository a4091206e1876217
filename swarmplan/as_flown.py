"""``swarmplan run --as-flown``: an offline run planned as the daemon plans the simulator's planes
(mavlink_bridge/mission/flown_planning.py)."""

from __future__ import annotations

from mavlink_bridge.mission.flown_planning import flight_margin_km, planning_scenario
from mavlink_bridge.mission.options import DaemonOptions
from mavlink_bridge.vehicles.airframe import (
    airframe_from_params,
    fleet_plane_model,
    separation_margin_km,
)
from mavlink_bridge.vehicles.airframe import threat_margin_km as airframe_threat_margin_km
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from planner.scenario import Scenario
from sim_gateway.parameters import default_specs


def simulator_planning_scenario(scenario: Scenario, steps: int | None = None) -> Scenario:
    """``scenario`` as a daemon with its default options plans it for ``steps`` decision steps,
    flying the airframes the simulator reports: each vehicle's parameter defaults, read as the
    daemon reads them at launch (``airframe_from_params``, ``MissionContext.use_airframes``)."""
    cfg = scenario.config
    options = DaemonOptions(connect=[])
    airframes = []
    for sysid in range(1, scenario.uav_count + 1):
        vehicle = VehicleState(sysid, link=None)  # type: ignore[arg-type]  # never connected
        specs = default_specs(sysid, cfg.speed_mps, scenario.altitude_m)
        vehicle.params.update({spec.name: spec.default for spec in specs})
        airframes.append(airframe_from_params(vehicle, cfg))
    plane = fleet_plane_model(airframes, cfg, options.airspeed_range_mps, options.bank_limit_deg)
    predicted = options.predicted_threat_margin_km
    margin = flight_margin_km(airframe_threat_margin_km(plane, predicted), plane, predicted)
    separation = separation_margin_km(plane, options.predicted_separation_margin_km)
    return planning_scenario(
        scenario,
        steps or scenario.steps,
        separation,
        options.home_reserve_extra_steps,
        margin,
    )
