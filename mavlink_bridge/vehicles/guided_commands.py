"""Commands to vehicles with acknowledgement and retry: arm, mode changes, guided reposition
(COMMAND_INT MAV_CMD_DO_REPOSITION), airspeed (MAV_CMD_DO_CHANGE_SPEED) and engagement requests
(camera capture).

``send_commands`` sends a batch (one command per vehicle, to many vehicles at once), pumps the
link until each has its COMMAND_ACK, and resends what is unanswered. COMMAND_LONG retries carry
an increasing ``confirmation``; the vehicle's answer to any attempt counts.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

from mavlink_bridge.vehicles.swarm_link import SwarmLink
from mavlink_bridge.vehicles.vehicle_state import CommandAck, VehicleState
from mavlink_wire.protocol import (
    AUTOPILOT_COMPONENT_ID,
    CAMERA_COMPONENT_ID,
    command_name,
    mavlink,
    result_name,
)
from planner.errors import UserError


class CommandRefusedError(UserError):
    """A vehicle answered a command with a result other than ACCEPTED, or never answered."""


@dataclass
class Command:
    """One command to one vehicle."""

    vehicle: VehicleState
    command: int
    params: tuple[float, float, float, float, float, float, float] = (0, 0, 0, 0, 0, 0, 0)
    as_int: bool = False  # COMMAND_INT (x, y as int lat/lon * 1e7) instead of COMMAND_LONG
    frame: int = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    target_component: int = AUTOPILOT_COMPONENT_ID
    attempts: int = 0
    ack: CommandAck | None = None
    #: for a COMMAND_ACK that echoes which request it answers (result_param1 = ``progress``):
    #: the value it must carry, so a late or duplicated ACK of an earlier request is not taken
    echo: int | None = None
    _serial_before: int = field(default=0, repr=False)

    @property
    def serial_before(self) -> int:
        """The vehicle's ack counter when this command was (first) sent: newer acks may answer
        it."""
        return self._serial_before

    @property
    def key(self) -> tuple[int, int]:
        return (self.target_component, self.command)

    def answered_by(self, ack: CommandAck) -> bool:
        """True if ``ack`` (newer than the first send) answers this command."""
        return (
            ack.serial > self._serial_before
            and (ack.component, ack.command) == self.key
            and (self.echo is None or ack.progress == self.echo)
        )

    @property
    def accepted(self) -> bool:
        return self.ack is not None and self.ack.result == mavlink.MAV_RESULT_ACCEPTED

    def describe_failure(self) -> str:
        name = command_name(self.command)
        if self.ack is None:
            return f"vehicle {self.vehicle.key} did not answer {name} ({self.attempts} tries)"
        return f"vehicle {self.vehicle.key} refused {name}: {result_name(self.ack.result)}"

    def send(self) -> None:
        """Send (or resend) the command."""
        mav = self.vehicle.link_for(self.target_component).mav
        p = self.params
        sysid = self.vehicle.system_id
        if self.as_int:
            mav.command_int_send(
                sysid,
                self.target_component,
                self.frame,
                self.command,
                0,
                0,
                p[0],
                p[1],
                p[2],
                p[3],
                int(p[4]),
                int(p[5]),
                p[6],
            )
        else:
            mav.command_long_send(
                sysid, self.target_component, self.command, min(self.attempts, 255), *p
            )
        self.attempts += 1


def send_commands(
    link: SwarmLink,
    commands: list[Command],
    retry_interval_s: float = 0.3,
    max_attempts: int = 5,
    deadline: float | None = None,
) -> list[Command]:
    """Send every command, wait for their acknowledgements, resend the unanswered ones.

    Returns the commands with ``ack`` set (None where no answer came after ``max_attempts``, or
    by ``deadline``, a ``time.monotonic()`` instant). Never raises for a refusal: the caller
    decides what a refusal means."""
    for cmd in commands:
        cmd._serial_before = cmd.vehicle.ack_serial
        cmd.ack = None
        cmd.send()
    last_send = time.monotonic()

    def collect() -> bool:
        for cmd in commands:
            if cmd.ack is None:
                # every ack since the first send, oldest first: duplicated and late ones are in
                # there too, and an IN_PROGRESS only says the final answer is still to come
                for ack in list(cmd.vehicle.ack_log):
                    if not cmd.answered_by(ack):
                        continue
                    if ack.result == mavlink.MAV_RESULT_IN_PROGRESS:
                        cmd._serial_before = ack.serial
                        continue
                    cmd.ack = ack
                    break
        return all(c.ack is not None for c in commands)

    while not collect():
        now = time.monotonic()
        if deadline is not None and now >= deadline:
            break
        if now - last_send >= retry_interval_s:
            pending = [c for c in commands if c.ack is None and not c.vehicle.lost]
            if not pending or all(c.attempts >= max_attempts for c in pending):
                break
            for cmd in pending:
                if cmd.attempts < max_attempts:
                    cmd.send()
            last_send = now
        link.pump(0.005)
    return commands


def require_accepted(commands: list[Command]) -> None:
    """Raise CommandRefusedError (one line: vehicle and result) for the first non-accepted."""
    for cmd in commands:
        if not cmd.accepted:
            raise CommandRefusedError(cmd.describe_failure())


# ---------------------------------------------------------------------- the commands themselves


def arm_command(vehicle: VehicleState) -> Command:
    """MAV_CMD_COMPONENT_ARM_DISARM, param1 = 1 (arm)."""
    return Command(vehicle, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (1, 0, 0, 0, 0, 0, 0))


def set_mode_command(vehicle: VehicleState, custom_mode: int) -> Command:
    """MAV_CMD_DO_SET_MODE with the custom-mode flag and an ArduPlane mode number."""
    flag = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    return Command(vehicle, mavlink.MAV_CMD_DO_SET_MODE, (flag, custom_mode, 0, 0, 0, 0, 0))


def reposition_command(
    vehicle: VehicleState,
    lat_deg: float,
    lon_deg: float,
    altitude_m: float,
    loiter_radius_m: float = 0,
) -> Command:
    """COMMAND_INT MAV_CMD_DO_REPOSITION: fly to lat/lon at ``altitude_m`` above home.

    param1 = -1 (default speed), param2 = 1 (MAV_DO_REPOSITION_FLAGS_CHANGE_MODE: switch to
    GUIDED), param3 = loiter radius (0: the autopilot's default), param4 = NaN (keep yaw
    behaviour). ArduPlane accepts it only as COMMAND_INT."""
    return Command(
        vehicle,
        mavlink.MAV_CMD_DO_REPOSITION,
        (-1, 1, loiter_radius_m, math.nan, round(lat_deg * 1e7), round(lon_deg * 1e7), altitude_m),
        as_int=True,
        frame=mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    )


def change_speed_command(vehicle: VehicleState, airspeed_mps: float) -> Command:
    """MAV_CMD_DO_CHANGE_SPEED: param1 = 0 (airspeed), param2 = m/s, param3 = -1 (throttle
    unchanged). ArduPlane and PX4 act on it in GUIDED; ArduPlane refuses a speed outside
    [AIRSPEED_MIN, AIRSPEED_MAX] (FAILED from ArduPlane 4.8, DENIED from our simulator): any
    result but ACCEPTED is a refusal."""
    return Command(
        vehicle, mavlink.MAV_CMD_DO_CHANGE_SPEED, (0, float(airspeed_mps), -1, 0, 0, 0, 0)
    )


def request_message_command(vehicle: VehicleState, message_id: int) -> Command:
    """MAV_CMD_REQUEST_MESSAGE: the vehicle ACKs, then sends the message once."""
    return Command(vehicle, mavlink.MAV_CMD_REQUEST_MESSAGE, (message_id, 0, 0, 0, 0, 0, 0))


def engagement_command(vehicle: VehicleState, sequence: int) -> Command:
    """An engagement request: MAV_CMD_IMAGE_START_CAPTURE to the camera (component 100), one
    image (param3 = 1, param2 = 0 interval), param4 = the engagement's sequence number (a retry
    with the same number gets the same outcome). The ACK's result_param2 is the serviced target
    id (0: none within the engage radius). Never a weapon or payload command."""
    return Command(
        vehicle,
        mavlink.MAV_CMD_IMAGE_START_CAPTURE,
        (0, 0, 1, sequence, 0, 0, 0),
        target_component=CAMERA_COMPONENT_ID,
        echo=sequence % 256,  # the camera's ACK carries the sequence number's low byte
    )
