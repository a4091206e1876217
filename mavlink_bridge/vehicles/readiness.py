"""Ready means ready: wait until every vehicle can really arm, then arm it, within one window.

An autopilot that reports MAV_STATE_STANDBY has only finished booting. ArduPlane SITL reports
STANDBY ~0.1 s after boot and refuses to arm for ~20 s more of its own clock ("Arm: Accels
inconsistent", "AHRS: waiting for home") until its EKF uses GPS; three arm tries 1 s apart
(the old launch) failed at real time. A vehicle is *ready to arm* here when

* its autopilot's pre-arm checks pass, where it reports them: SYS_STATUS bit
  ``MAV_SYS_STATUS_PREARM_CHECK`` set in ``onboard_control_sensors_present`` and ``_enabled``
  means the autopilot reports them, and the same bit in ``_health`` that they pass (ArduPilot
  4.1+ and PX4 fill it in);
* it has a 3D GPS fix (GPS_RAW_INT ``fix_type`` >= 3), where it reports a GPS at all;
* its home position is known (HOME_POSITION, asked for with MAV_CMD_REQUEST_MESSAGE every few
  seconds until it comes): the launch point is the UAV's start and return point.

``arm_when_ready`` waits for that, arms each vehicle as soon as it is ready, and tries again
(a refusal is normal while sensors settle) until every vehicle is armed or the window
(``swarmplan daemon --ready-timeout``) is over; then it names each vehicle still not armed and
why, with its newest PreArm STATUSTEXT reasons, in one line. A progress line goes out every
``progress_period_s``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

from mavlink_bridge.vehicles.guided_commands import Command, arm_command, request_message_command
from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_bridge.vehicles.vehicle_state import VehicleState
from mavlink_wire.protocol import mavlink, result_name
from planner.errors import UserError

PREARM_BIT = mavlink.MAV_SYS_STATUS_PREARM_CHECK
GPS_BIT = mavlink.MAV_SYS_STATUS_SENSOR_GPS
#: ask again for HOME_POSITION after this long without it (wall s)
HOME_REQUEST_PERIOD_S = 3.0
#: pause between arm attempts of a vehicle that refused, or accepted and is not armed yet (wall s)
ARM_RETRY_S = 1.0
#: how long an answer owed at this very instant is waited for without granting time to a
#: lockstep simulator (wall s): the heartbeat that shows an accepted arm, the HOME_POSITION that
#: follows an accepted request for it. Three heartbeat periods: at one (1 s), a heartbeat lost
#: or late on a loaded machine granted a decision period meanwhile, and the seed's planes armed
#: 10 simulated s later, into another mission
ANSWER_WAIT_S = 3.0


class NotReadyError(UserError):
    """Vehicles that could not be armed within the readiness window."""


@dataclass(frozen=True)
class Readiness:
    """What stands between one vehicle and arming, from its telemetry."""

    key: VehicleKey
    reports_prearm: bool
    prearm_ok: bool
    reports_gps: bool
    gps_fix_type: int
    has_home: bool
    initialised: bool

    @property
    def ready(self) -> bool:
        return not self.missing()

    def missing(self) -> list[str]:
        """Why it is not ready, in words (empty when ready)."""
        out = []
        if not self.initialised:
            out.append("still initialising")
        if self.reports_prearm and not self.prearm_ok:
            out.append("pre-arm checks failing")
        if self.reports_gps and self.gps_fix_type < mavlink.GPS_FIX_TYPE_3D_FIX:
            fix = "no GPS" if self.gps_fix_type < 0 else f"GPS fix type {self.gps_fix_type}"
            out.append(f"no 3D GPS fix ({fix})")
        if not self.has_home:
            out.append("no home position")
        return out


def readiness_of(vehicle: VehicleState) -> Readiness:
    """The vehicle's readiness from what it last reported."""
    reported = vehicle.sensors_present & vehicle.sensors_enabled
    reports_gps = vehicle.gps_fix_type >= 0 or bool(vehicle.sensors_present & GPS_BIT)
    return Readiness(
        key=vehicle.key,
        reports_prearm=bool(reported & PREARM_BIT),
        prearm_ok=bool(vehicle.sensors_health & PREARM_BIT),
        reports_gps=reports_gps,
        gps_fix_type=vehicle.gps_fix_type,
        has_home=vehicle.home is not None,
        initialised=vehicle.standby_or_active,
    )


def arm_when_ready(
    vehicles: list[VehicleState],
    window_s: float,
    send: Callable[[list[Command], int], list[Command]],
    wait: Callable[[Callable[[], bool], float], bool],
    progress: Callable[[str], None] | None = None,
    progress_period_s: float = 5.0,
    arm_attempts: int = 5,
    listen: Callable[[Callable[[], bool], float], bool] | None = None,
) -> None:
    """Arm every vehicle once it is ready (module docstring), retrying refusals, within
    ``window_s`` wall seconds. ``send(commands, attempts)`` sends commands (each up to
    ``attempts`` times) and collects their ACKs;
    ``wait(done, timeout_s)`` pumps the link (and grants time to a lockstep simulator);
    ``listen(done, timeout_s)`` pumps it without granting time (by default ``wait``): an
    accepted arm shows in the heartbeat of the same instant, and an accepted request for
    HOME_POSITION is followed by the message (each waited for up to ``ANSWER_WAIT_S``), so a
    lockstep seed arms at the same simulated instant however late the answers are.

    Raises NotReadyError naming every vehicle not armed at the end, what it lacks and its
    newest PreArm reasons."""
    started = time.monotonic()
    deadline = started + window_s
    next_progress = started + progress_period_s
    home_asked: dict[VehicleKey, float] = {}
    next_arm: dict[VehicleKey, float] = {}
    refusals: dict[VehicleKey, str] = {}

    def done() -> bool:
        return all(v.armed for v in vehicles)

    while not done():
        now = time.monotonic()
        if now >= deadline:
            break
        missing_home = [
            v
            for v in vehicles
            if v.home is None and now - home_asked.get(v.key, -1e9) >= HOME_REQUEST_PERIOD_S
        ]
        if missing_home:
            for v in missing_home:
                home_asked[v.key] = now
            # one try each: the message itself is what counts, and it is asked for again
            home = mavlink.MAVLINK_MSG_ID_HOME_POSITION
            asked = send([request_message_command(v, home) for v in missing_home], 1)
            answering = [cmd.vehicle for cmd in asked if cmd.accepted]
            if answering:  # the message follows its ACK (at the same instant of a lockstep clock)
                (listen or wait)(partial(_all_have_homes, answering), ANSWER_WAIT_S)
                now = time.monotonic()
        due = [
            v
            for v in vehicles
            if not v.armed and readiness_of(v).ready and now >= next_arm.get(v.key, 0.0)
        ]
        if due:
            sent = send([arm_command(v) for v in due], arm_attempts)
            accepted = [cmd.vehicle for cmd in sent if cmd.accepted]
            if accepted:  # the heartbeat that shows it, at the same instant of a lockstep clock
                (listen or wait)(partial(_all_armed, accepted), ANSWER_WAIT_S)
            for cmd in sent:
                # accepted or not, the next try waits (without the pause, a paced 20x mission
                # sent one vehicle 160 arm commands in the second before its heartbeat said armed)
                next_arm[cmd.vehicle.key] = time.monotonic() + ARM_RETRY_S
                if not cmd.accepted and not cmd.vehicle.armed:
                    refusals[cmd.vehicle.key] = (
                        result_name(cmd.ack.result) if cmd.ack else "no answer"
                    )
        if progress is not None and time.monotonic() >= next_progress:
            next_progress += progress_period_s
            progress(progress_line(vehicles, time.monotonic() - started, window_s))
        wait(lambda: done() or _newly_ready(vehicles, next_arm), 0.5)
    if done():
        return
    raise NotReadyError(_failure_line(vehicles, window_s, started, refusals))


def _all_armed(vehicles: list[VehicleState]) -> bool:
    return all(v.armed for v in vehicles)


def _all_have_homes(vehicles: list[VehicleState]) -> bool:
    return all(v.home is not None for v in vehicles)


def _newly_ready(vehicles: list[VehicleState], next_arm: dict[VehicleKey, float]) -> bool:
    now = time.monotonic()
    return any(
        not v.armed and now >= next_arm.get(v.key, 0.0) and readiness_of(v).ready for v in vehicles
    )


def progress_line(vehicles: list[VehicleState], elapsed_s: float, window_s: float) -> str:
    """``readiness: 2/3 armed, 0 ready; vehicle 3: pre-arm checks failing (...) (12/120 s)``."""
    armed = sum(v.armed for v in vehicles)
    waiting = []
    for v in vehicles:
        if v.armed:
            continue
        missing = readiness_of(v).missing()
        reasons = v.prearm_reasons() if "pre-arm checks failing" in missing else []
        text = ", ".join(missing) if missing else "ready, arming"
        if reasons:
            text += f" ({'; '.join(reasons)})"
        waiting.append(f"vehicle {v.key}: {text}")
    return (
        f"readiness: {armed}/{len(vehicles)} armed; {'; '.join(waiting)} "
        f"({elapsed_s:.0f}/{window_s:g} s)"
    )


def _failure_line(
    vehicles: list[VehicleState], window_s: float, started: float, refusals: dict[VehicleKey, str]
) -> str:
    parts = []
    for v in vehicles:
        if v.armed:
            continue
        why = readiness_of(v).missing()
        if not why:
            why = [f"arming refused ({refusals.get(v.key, 'no answer')})"]
        reasons = v.prearm_reasons(since_s=started - 1.0)
        text = f"vehicle {v.key} ({', '.join(why)}"
        text += f": {'; '.join(reasons)})" if reasons else ")"
        parts.append(text)
    return (
        f"not ready to arm within {window_s:g} s: {'; '.join(parts)}; fix what the autopilot "
        f"reports, or give it longer with --ready-timeout"
    )
