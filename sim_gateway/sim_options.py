"""How the simulator runs and where its vehicles talk (:class:`SimOptions`, the settings of
``swarmplan sim``), checked before anything opens: a setting it cannot run with is a
:class:`SimulatorError` that says what to change.
"""

from __future__ import annotations

import dataclasses
import math
import socket
from dataclasses import dataclass

from planner.errors import UserError
from planner.scenario import Scenario

#: one simulator's vehicles take system ids 1..250 of its MAVLink network; 251-255 are left to
#: ground stations (MAVProxy and the daemon 255; MAVSDK's 245 is a vehicle's beyond 244)
MAX_VEHICLES = 250
MAVLINK_NOTE = f"{MAX_VEHICLES} (the system ids of one MAVLink network)"


class SimulatorError(UserError):
    """The simulator cannot start with these settings; the message says what to change."""


@dataclass(frozen=True)
class RadioOptions:
    """The swarm radio's range (km), loss probability, latency (ms) and shared bandwidth
    (kbit/s); ``inf`` range or bandwidth: unlimited."""

    range_km: float = math.inf
    loss: float = 0.0
    latency_ms: float = 0.0
    kbps: float = math.inf

    def validate(self) -> None:
        if math.isnan(self.range_km) or self.range_km <= 0:
            raise SimulatorError(
                f"--radio-range-km must be a positive distance in km, got {self.range_km}; "
                "e.g. --radio-range-km 20"
            )
        if not (math.isfinite(self.loss) and 0.0 <= self.loss <= 1.0):
            raise SimulatorError(
                f"--radio-loss must be a probability in [0, 1], got {self.loss}; e.g. 0.1 for 10 %"
            )
        if not (math.isfinite(self.latency_ms) and 0.0 <= self.latency_ms <= 60_000):
            raise SimulatorError(
                f"--radio-latency-ms must be in [0, 60000] ms, got {self.latency_ms}"
            )
        if math.isnan(self.kbps) or self.kbps <= 0:
            raise SimulatorError(
                f"--radio-kbps must be a positive rate in kbit/s, got {self.kbps}; "
                "e.g. --radio-kbps 57.6 (a SiK radio's air rate)"
            )


@dataclass(frozen=True)
class SimOptions:
    """How the simulator runs and where its vehicles talk."""

    seed: int = 0
    vehicles: int | None = None  # None: the scenario's UAV count (from ``first_uav``: the rest)
    #: fly the scenario's UAVs (as it is) from this one (0-based) on, as system ids 1.. of this
    #: network: a swarm of more than MAX_VEHICLES flies as several simulators (the daemon's
    #: ``--connect SPEC@FIRST``, mavlink_bridge/vehicles/vehicle_key.py). None: ``vehicles``
    #: makes a scenario of that many UAVs (random starts)
    first_uav: int | None = None
    speedup: float = 1.0
    fast: bool = False
    tick_s: float = 0.1
    gcs_host: str = "127.0.0.1"
    gcs_port: int = 14550
    per_vehicle_port_base: int | None = None  # vehicle i sends to base + i instead of gcs_port
    bind_host: str = "127.0.0.1"
    bind_port_base: int = 0  # vehicle i binds base + i; 0: any free port
    boot_s: float = 20.0
    airborne: bool = False
    position_rate_hz: float = 10.0
    signing_key: bytes | None = None  # MAVLink 2 signing (sim_gateway/signing.py); None: off
    lockstep: bool = False  # hold at the horizon the ground station grants (SYSTEM_TIME)
    lockstep_timeout_s: float = 10.0  # wall s of ground-station silence that end the lock
    truth_port: int | None = None  # send the true targets to 127.0.0.1:PORT (truth_feed.py)
    radio: RadioOptions = RadioOptions()  # the swarm link between the nodes (radio.py)
    #: a ground station hears the swarm link (radio.GroundRadio): what it hears goes to
    #: gcs_host:PORT; None: no ground station on the channel
    radio_ground_port: int | None = None
    #: where that ground station's antenna is, mission frame km; None: the area's centre
    radio_ground_km: tuple[float, float] | None = None

    def validate(self) -> None:
        self.radio.validate()
        if self.fast and self.lockstep:
            raise SimulatorError(
                "--fast and --lockstep exclude each other: lockstep already runs as fast as the "
                "ground station allows; drop one"
            )
        if not (math.isfinite(self.lockstep_timeout_s) and self.lockstep_timeout_s > 0):
            raise SimulatorError(
                f"--lockstep-timeout must be a positive number of seconds, got "
                f"{self.lockstep_timeout_s}"
            )
        if not (math.isfinite(self.speedup) and self.speedup > 0):
            raise SimulatorError(
                f"--speedup must be a positive number, got {self.speedup}; e.g. --speedup 50"
            )
        if not (math.isfinite(self.tick_s) and 0.001 <= self.tick_s <= 1.0):
            raise SimulatorError(
                f"--tick-s must be in [0.001, 1] s, got {self.tick_s}; 0.1 is the default"
            )
        if not (math.isfinite(self.boot_s) and 0 <= self.boot_s <= 600):
            raise SimulatorError(f"--boot-s must be in [0, 600] s, got {self.boot_s}")
        if not (math.isfinite(self.position_rate_hz) and 0 < self.position_rate_hz <= 50):
            raise SimulatorError(f"--telemetry-hz must be in (0, 50], got {self.position_rate_hz}")
        if self.first_uav is not None and self.first_uav < 0:
            raise SimulatorError(f"--first-uav must be 0 or more, got {self.first_uav}")
        if self.vehicles is not None and not 1 <= self.vehicles <= MAX_VEHICLES:
            raise SimulatorError(f"--vehicles must be in 1..{MAX_VEHICLES}, got {self.vehicles}")
        for name, port, low in (
            ("--gcs-port", self.gcs_port, 1),
            ("--per-vehicle-ports", self.per_vehicle_port_base, 1),
            ("--bind-base-port", self.bind_port_base, 0),
            ("--truth-port", self.truth_port, 1),
            ("--radio-ground-port", self.radio_ground_port, 1),
        ):
            if port is not None and not low <= port <= 65535:
                raise SimulatorError(f"{name} must be a UDP port in {low}..65535, got {port}")


def resolve_gcs_host(host: str) -> str:
    """The IPv4 address of ``--gcs-host`` (looked up once: the vehicles' ground station is
    bound to it, sim_gateway/lockstep.py)."""
    try:
        return socket.getaddrinfo(host, None, socket.AF_INET, socket.SOCK_DGRAM)[0][4][0]
    except (OSError, UnicodeError) as exc:
        raise SimulatorError(
            f"--gcs-host {host!r} is not an IPv4 address or a name this machine can resolve "
            f"({exc}); e.g. --gcs-host 127.0.0.1"
        ) from None


def flown_uavs(
    scenario: Scenario, count: int | None, first_uav: int | None
) -> tuple[Scenario, range]:
    """The scenario (``with_vehicle_count`` without ``first_uav``) and the UAVs of it this
    simulator flies: ``count`` (default: the rest) from ``first_uav`` on, at most
    ``MAX_VEHICLES``."""
    if first_uav is None:
        scenario = with_vehicle_count(scenario, count)
        return scenario, range(scenario.uav_count)
    n = scenario.uav_count - first_uav if count is None else count
    if n < 1 or first_uav + n > scenario.uav_count:
        raise SimulatorError(
            f"--first-uav {first_uav} with {n} vehicles passes the {scenario.uav_count} UAVs of "
            f"scenario {scenario.name!r}; lower --first-uav or --vehicles"
        )
    if n > MAX_VEHICLES:
        raise SimulatorError(
            f"UAVs {first_uav}.. of scenario {scenario.name!r} are {n} vehicles and one "
            f"simulator serves at most {MAVLINK_NOTE}; give --vehicles {MAX_VEHICLES} or fewer"
        )
    return scenario, range(first_uav, first_uav + n)


def with_vehicle_count(scenario: Scenario, count: int | None) -> Scenario:
    """The scenario with ``count`` UAVs (random starts only: fixed starts fix the count), at most
    ``MAX_VEHICLES`` of them."""
    if count is None or count == scenario.uav_count:
        if scenario.uav_count > MAX_VEHICLES:
            raise SimulatorError(
                f"scenario {scenario.name!r} has {scenario.uav_count} UAVs and one simulator "
                f"serves at most {MAVLINK_NOTE}; fly it offline (swarmplan run)"
            )
        return scenario
    if scenario.uav_starts is not None:
        raise SimulatorError(
            f"scenario {scenario.name!r} fixes {scenario.uav_count} UAV starts; drop --vehicles "
            "or use a scenario with random starts"
        )
    return dataclasses.replace(scenario, uav_count=count)
