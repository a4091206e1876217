"""Flying the stored mission in AUTO, the way ArduPlane does: item by item (DO items at once,
DO_JUMP with its repeat count, loiter times and turns, take-off and landing), what the
vehicle does when its kinematics reach an item's point or altitude, and the MISSION_CURRENT
that reports where it is. :class:`AutoMission` is a base class of every
:class:`~sim_gateway.vehicle.Vehicle`; the upload and download of missions is
``sim_gateway/mission_protocol.py``.
"""

from __future__ import annotations

import math
from typing import Protocol

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim_gateway import flight_modes as modes
from sim_gateway.fixed_wing import FleetKinematics
from sim_gateway.mission_store import MissionItem, MissionStore
from sim_gateway.parameters import ParameterSet


class MissionHost(Protocol):
    """What flying a mission needs from the simulator: the clock and the map's origin."""

    sim_time_s: float

    def home_amsl_m(self) -> float: ...
    def geodetic_to_local(self, lat_deg: float, lon_deg: float) -> tuple[float, float]: ...


def mission_current(missions: MissionStore, mode: int) -> mavlink.MAVLink_message:
    """MISSION_CURRENT, streamed and sent whenever the current item changes."""
    total = max(len(missions.mission()) - 1, 0)
    return mavlink.MAVLink_mission_current_message(
        missions.current_seq,
        total=total,
        mission_state=mavlink.MISSION_STATE_NO_MISSION
        if total == 0
        else mavlink.MISSION_STATE_ACTIVE
        if mode == modes.AUTO
        else mavlink.MISSION_STATE_NOT_STARTED,
        mission_mode=int(mode == modes.AUTO),
    )


class AutoMission:
    """The AUTO mission behaviour of a vehicle (a part of :class:`~sim_gateway.vehicle.Vehicle`).

    It reads and sets the vehicle state declared below, and calls the vehicle's ``send``,
    ``statustext``, ``set_mode``, ``airborne``, ``land_now``, ``return_to_launch`` and
    ``start_takeoff_if_due``.
    """

    index: int
    host: MissionHost
    fleet: FleetKinematics
    params: ParameterSet
    missions: MissionStore
    mode: int
    armed: bool
    item_wait_until_s: float | None  # AUTO loiter-time / turns deadline
    item_arrived: bool
    jumps_left: dict[int, int]  # DO_JUMP item seq -> repeats left

    def current_item_command(self) -> int | None:
        items = self.missions.mission()
        seq = self.missions.current_seq
        return items[seq].command if 0 <= seq < len(items) else None

    def item_relative_alt(self, item: MissionItem) -> float:
        return item.z if item.is_relative_alt() else item.z - self.host.home_amsl_m()

    def start_mission_item(self, seq: int) -> None:
        """Make item ``seq`` current and start flying it (DO items run at once)."""
        items = self.missions.mission()
        for _ in range(len(items) + 1):  # bounded: DO items and jumps cannot loop forever
            if seq >= len(items):
                self.finish_mission()
                return
            self.missions.current_seq = seq
            self.item_wait_until_s = None
            self.item_arrived = False
            item = items[seq]
            self.send_mission_current()
            next_seq = self.begin_item(item)
            if next_seq is None:
                return
            seq = next_seq
        self.finish_mission()

    def begin_item(self, item: MissionItem) -> int | None:
        """Start one item; returns the next seq when the item completes at once (DO items)."""
        i, fleet, p = self.index, self.fleet, self.params
        cmd = item.command
        if cmd == mavlink.MAV_CMD_DO_CHANGE_SPEED:
            if p["AIRSPEED_MIN"] <= item.param2 <= p["AIRSPEED_MAX"]:
                fleet.set_airspeed(i, item.param2)
            return item.seq + 1
        if cmd == mavlink.MAV_CMD_DO_JUMP:
            target, repeat = int(item.param1), int(item.param2)
            left = self.jumps_left.setdefault(item.seq, repeat)
            if left == 0 or not 1 <= target < len(self.missions.mission()):
                return item.seq + 1
            if left > 0:
                self.jumps_left[item.seq] = left - 1
            return target
        if cmd not in (
            mavlink.MAV_CMD_NAV_TAKEOFF,
            mavlink.MAV_CMD_NAV_WAYPOINT,
            mavlink.MAV_CMD_NAV_LOITER_UNLIM,
            mavlink.MAV_CMD_NAV_LOITER_TIME,
            mavlink.MAV_CMD_NAV_LOITER_TURNS,
            mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH,
            mavlink.MAV_CMD_NAV_LAND,
        ):
            return item.seq + 1  # other DO commands: nothing to fly (never a payload release)
        if cmd == mavlink.MAV_CMD_NAV_TAKEOFF:
            alt = self.item_relative_alt(item)
            if self.airborne:
                fleet.target_alt_m[i] = max(alt, float(fleet.alt_m[i]))
                if fleet.alt_m[i] >= alt - 1.0:
                    self.mission_item_reached(item.seq)
                    return item.seq + 1
            else:
                self.start_takeoff_if_due()
            return None
        if cmd == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self.return_to_launch()
            return None
        x_m, y_m = self.host.geodetic_to_local(item.lat_deg, item.lon_deg)
        if item.x == 0 and item.y == 0:  # "here" (as ArduPilot reads a 0,0 location)
            x_m, y_m = float(fleet.x_m[i]), float(fleet.y_m[i])
        if self.airborne and cmd != mavlink.MAV_CMD_NAV_LAND:
            alt = self.item_relative_alt(item)
            if alt > 0:
                fleet.target_alt_m[i] = alt
        if cmd == mavlink.MAV_CMD_NAV_WAYPOINT:
            fleet.fly_to(i, x_m, y_m, p["WP_RADIUS"], None)
        else:
            radius = (
                item.param3 if math.isfinite(item.param3) and item.param3 else p["WP_LOITER_RAD"]
            )
            fleet.fly_to(i, x_m, y_m, p["WP_RADIUS"], radius)
        return None

    def on_arrived(self) -> None:
        """The kinematics reached the PURSUIT point of this vehicle."""
        if self.mode != modes.AUTO:
            return
        items = self.missions.mission()
        seq = self.missions.current_seq
        if not 0 <= seq < len(items):
            return
        item = items[seq]
        cmd = item.command
        self.item_arrived = True
        if cmd in (mavlink.MAV_CMD_NAV_WAYPOINT, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH):
            self.advance_mission(seq)
        elif cmd == mavlink.MAV_CMD_NAV_LOITER_TIME:
            self.item_wait_until_s = self.host.sim_time_s + max(item.param1, 0.0)
        elif cmd == mavlink.MAV_CMD_NAV_LOITER_TURNS:
            radius = float(self.fleet.effective_orbit_radius_m()[self.index])
            lap_s = 2 * math.pi * radius / max(float(self.fleet.airspeed_mps[self.index]), 1.0)
            self.item_wait_until_s = self.host.sim_time_s + max(item.param1, 0.0) * lap_s
        elif cmd == mavlink.MAV_CMD_NAV_LAND:
            self.fleet.target_alt_m[self.index] = 0.0

    def on_climbed(self) -> None:
        """The kinematics reached this vehicle's altitude target."""
        i = self.index
        if self.mode == modes.TAKEOFF:
            self.fleet.orbit(
                i, float(self.fleet.x_m[i]), float(self.fleet.y_m[i]), self.params["WP_LOITER_RAD"]
            )
        elif self.mode == modes.AUTO:
            cmd = self.current_item_command()
            if cmd == mavlink.MAV_CMD_NAV_TAKEOFF:
                self.advance_mission(self.missions.current_seq)
            elif (
                cmd == mavlink.MAV_CMD_NAV_LAND and self.item_arrived and self.fleet.alt_m[i] <= 1.0
            ):
                self.land_now()
                self.armed = False
                self.statustext("Landed, disarmed")
                self.advance_mission(self.missions.current_seq)

    def on_timer(self) -> None:
        """Called when a pending AUTO deadline may have passed."""
        if self.item_wait_until_s is not None and self.host.sim_time_s >= self.item_wait_until_s:
            self.item_wait_until_s = None
            if self.mode == modes.AUTO:
                self.advance_mission(self.missions.current_seq)

    def advance_mission(self, seq: int) -> None:
        self.mission_item_reached(seq)
        if self.mode == modes.AUTO and self.armed:
            self.start_mission_item(seq + 1)

    def mission_item_reached(self, seq: int) -> None:
        self.send(mavlink.MAVLink_mission_item_reached_message(seq))

    def finish_mission(self) -> None:
        self.missions.current_seq = max(len(self.missions.mission()) - 1, 0)
        self.statustext("Mission complete, changing mode to RTL")
        self.set_mode(modes.RTL)

    def send_mission_current(self) -> None:
        self.send(mission_current(self.missions, self.mode))

    def set_current_item(self, seq: int) -> bool:
        """MISSION_SET_CURRENT / MAV_CMD_DO_SET_MISSION_CURRENT: False when there is no item
        ``seq``. In AUTO the vehicle flies to it at once (item 0, home, counts as item 1)."""
        if not 0 <= seq < len(self.missions.mission()):
            return False
        if self.mode == modes.AUTO:
            self.start_mission_item(max(seq, 1))
        else:
            self.missions.current_seq = seq
            self.send_mission_current()
        return True
