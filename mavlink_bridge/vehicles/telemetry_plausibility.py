"""What the daemon believes of what it hears: a frame changes a vehicle's state (its reply
address, liveness, position, clock, status) only if it is authentic or, without signing,
plausible for that vehicle. Everything else is dropped and counted (``PlausibilityCounts``, the
result's ``plausibility``), never believed.

Rules, in the order ``SwarmLink`` applies them (docs/reliability.md, "Believing only what is
authentic"):

1. **Signing on**: an unsigned frame (RADIO_STATUS / RADIO pass the signature check unsigned,
   as ArduPilot accepts them from radios) changes nothing: it goes to the .tlog and is counted
   as ``unsigned_ignored``. Signed frames are authentic (signature and replay checked before).
2. **One address per vehicle component**: a vehicle exists once its autopilot (component 1)
   announces it: a HEARTBEAT that carries a vehicle type (``swarm_link.claims_vehicle``); it is
   bound to the address (and endpoint) of that HEARTBEAT. Another component is bound by its own
   HEARTBEAT, or by a frame from the autopilot's address (routed through it; this one wins over
   a HEARTBEAT heard elsewhere first, which may have been a stranger's). Any other
   frame of a (system, component) bound to nothing binds nothing and is dropped (``unbound``:
   the frames of senders that never became the vehicle; a vehicle's own frames before its
   first HEARTBEAT are taken back from it when it binds).
   A frame of it from another address is ``second_address``; each such address is said once in
   a line and counted once (``address_conflicts``), and nothing is sent to it. A binding moves
   only when the bound address has been silent for ``move_after_s`` wall seconds, the daemon
   counts the vehicle as gone (lost to silence or a closed link, ``vehicle_loss.py``: never in
   a whole-swarm pause of a lockstep simulator, when every bound address is silent and a
   stranger could step in), *and* the new address announces the component again (for the
   autopilot: the vehicle type it registered with): a reboot, a new socket; the move is
   counted (``address_moves``) and said.
3. **Fields in range**: positions on Earth, altitude within ``altitude_range_m``, velocities
   below ``max_ground_speed_mps``, heading 0..359.99 deg or unknown, HEARTBEAT enums in range and
   the vehicle type it registered with (``out_of_range``). Before a vehicle's first believed
   position, one within ~100 m of latitude 0, longitude 0 is an autopilot's placeholder while
   its position estimate has no origin (ArduPlane SITL's first ~8 s), not a place
   (``no_position``; once a position is believed, a jump there is ``too_fast``).
4. **Time** (``time_boot_ms`` of GLOBAL_POSITION_INT): older than the newest believed one is a
   delayed or reordered frame (``stale_positions``); ahead of it by more than the vehicle's
   clock can have run (lockstep: past the granted horizon, even a first position; paced: the
   wall time since x its clock rate, the declared ``time_scale`` or the rate measured over its
   time base, x ``clock_slack``, + ``clock_slack_ms``) is ``time_jump``.
5. **Speed**: a position farther from the last believed one than ``max_ground_speed_mps`` x
   the time between them (+ ``position_slack_m``) is ``too_fast``; a sensor look farther than
   that from the vehicle's believed position at its time likewise.

A real reboot restarts ``time_boot_ms``, a teleported (reset) simulator vehicle jumps: both are
**a new time base**, accepted explicitly only when it is the only one left: ``rebase_frames``
frames failing rules 4-5 that agree with each other (time increasing, speed plausible between
them), over at least ``rebase_after_s`` wall seconds, with no frame of the old base believed
meanwhile (``clock_rebases``, said as a warning). A replay or a spoofer interleaved with the
live vehicle never gets there: each frame of the live base resets the candidate. In lockstep a
position stamped past the granted horizon is never believed nor a new base: the simulator holds
there, so such a clock runs free (lockstep released), which ``LockstepClock`` says and stops at.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

from mavlink_bridge.vehicles.vehicle_key import VehicleKey
from mavlink_wire.protocol import AUTOPILOT_COMPONENT_ID, mavlink

#: the largest MAV_STATE (system_status) and MAV_RESULT values a vehicle can send
_MAX_MAV_STATE = mavlink.MAV_STATE_FLIGHT_TERMINATION
_EARTH_RADIUS_M = 6_371_000.0
#: the clock rate assumed before one could be measured (a SITL's --speedup is rarely above)
UNMEASURED_RATE = 1000.0


@dataclass(frozen=True)
class PlausibilityLimits:
    """What a vehicle of the swarm can do (defaults: a fixed-wing of the paper's class)."""

    #: fastest ground speed believed: airspeed up to 150 m/s (1.5 v) plus wind, with margin
    max_ground_speed_mps: float = 300.0
    #: GPS noise and the rounding of degE7 / decimetre fields, on top of the speed bound
    position_slack_m: float = 150.0
    altitude_range_m: tuple[float, float] = (-1_000.0, 20_000.0)
    #: wall seconds a bound address must be silent before a vehicle may move to another one
    #: (the daemon's ``lost_after_s``: only a vehicle that counts as lost moves; a loaded
    #: machine can hold a simulator silent for a second, and a spoofer must not step in then)
    move_after_s: float = 3.0
    #: the least a new time base must last (wall seconds, frames) before it replaces the old one
    rebase_after_s: float = 1.0
    rebase_frames: int = 3
    #: lockstep: the vehicles' clock cannot pass the horizon granted to them (``granted_ms``)
    lockstep: bool = False
    #: the vehicles' clock speed (SITL --speedup, the daemon's --time-scale); a clock may run
    #: this many times faster than declared, plus this much, before a jump counts as implausible
    time_scale: float = 1.0
    clock_slack: float = 4.0
    clock_slack_ms: float = 2_000.0
    #: a sensor look older than this (vehicle clock) than the newest position is not believed
    oldest_look_ms: float = 60_000.0


@dataclass
class PlausibilityCounts:
    """Frames dropped (and events accepted) by rule; the result's ``plausibility``."""

    unsigned_ignored: int = 0
    second_address: int = 0
    out_of_range: int = 0
    time_jump: int = 0
    too_fast: int = 0
    stale_positions: int = 0
    no_position: int = 0
    address_moves: int = 0
    clock_rebases: int = 0
    unbound: int = 0
    address_conflicts: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


#: latitude and longitude (1e-7 deg) both within this of 0: no position yet (~100 m)
_NO_POSITION_E7 = 10_000
#: second addresses remembered (each counted once in ``address_conflicts``), and said in a line
_CONFLICTS_REMEMBERED = 1024
#: (system id, address) pairs whose unbound frames are remembered (a vehicle's own, before its
#: first HEARTBEAT, are taken back when it binds); beyond, a new sender's frames just count
_SENDERS_REMEMBERED = 4096
_CONFLICTS_SAID = 10


@dataclass
class _Fix:
    """A believed (or candidate) position: vehicle clock and place."""

    time_ms: int
    lat_deg: float
    lon_deg: float
    wall_s: float


@dataclass
class _Binding:
    """Where one (system, component) is heard from, and when it was last heard there."""

    where: tuple[int, Any]  # (id(endpoint), address)
    heard_s: float


def _place(where: tuple[int, Any]) -> str:
    """An address as said in a line: ``host:port``, or a connection (TCP, udpout)."""
    address = where[1]
    return f"{address[0]}:{address[1]}" if address is not None else "its connection"


@dataclass
class VehicleTrust:
    """The plausibility state of one vehicle: its bound addresses, its believed clock and
    position, and the candidate new time base."""

    system_id: VehicleKey = VehicleKey(0, 0)
    vehicle_type: int | None = None
    bindings: dict[int, _Binding] = field(default_factory=dict)  # by component id
    fix: _Fix | None = None
    #: the first believed position of the current time base (its clock rate is measured from it)
    base: _Fix | None = None
    candidates: list[_Fix] = field(default_factory=list)
    #: lockstep: positions in a row stamped past the granted horizon
    past_grant: int = 0


def _rebase_notice(sysid: VehicleKey, old: _Fix, new: _Fix) -> str:
    """What a new time base of vehicle ``sysid`` means: a clock that went back restarted; one
    that jumped ahead with its position (an autopilot whose position estimate settles after
    boot: ArduPlane SITL's first reports) moved on faster than it can fly."""
    times = f"time {old.time_ms / 1e3:.1f} s -> {new.time_ms / 1e3:.1f} s"
    if new.time_ms < old.time_ms:
        return (
            f"vehicle {sysid}: clock restarted ({times}, a reboot or reset): "
            "following its new time base"
        )
    km = ground_distance_m(old.lat_deg, old.lon_deg, new.lat_deg, new.lon_deg) / 1e3
    return (
        f"vehicle {sysid}: position jumped {km:.1f} km ({times}, faster than it can fly: "
        f"a reset, or its position estimate settling): following its new reports"
    )


def ground_distance_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Great-circle distance (haversine), metres."""
    p1, p2 = math.radians(lat1), math.radians(lat2)
    dp, dl = p2 - p1, math.radians(lon2 - lon1)
    h = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2 * _EARTH_RADIUS_M * math.asin(min(1.0, math.sqrt(h)))


def on_earth(lat_e7: int, lon_e7: int) -> bool:
    """A latitude / longitude pair (degrees * 1e7) that can be a place."""
    return -90e7 <= lat_e7 <= 90e7 and -180e7 <= lon_e7 <= 180e7


class PlausibilityFilter:
    """Judges every frame of a registered vehicle before it may change that vehicle's state."""

    def __init__(self, limits: PlausibilityLimits | None = None) -> None:
        self.limits = limits or PlausibilityLimits()
        self.counts = PlausibilityCounts()
        self.vehicles: dict[VehicleKey, VehicleTrust] = {}
        #: lockstep: the horizon granted to the vehicles (ms); their clock cannot pass it
        self.granted_ms: int | None = None
        #: lines worth saying (a clock rebase, an address move), taken by the daemon
        self.notices: list[str] = []
        #: (system, component, where) of every second address refused so far
        self._conflicts: set[tuple[VehicleKey, int, tuple[int, Any]]] = set()
        #: frames of (system, where) dropped while nothing was bound (``unbound``)
        self._unbound: dict[tuple[VehicleKey, tuple[int, Any]], int] = {}

    # ------------------------------------------------------------------ address

    def admit_address(
        self,
        sysid: VehicleKey,
        compid: int,
        where: tuple[int, Any],
        now_s: float,
        announces: bool,
        may_move: bool = True,
    ) -> str:
        """Where a frame of (``sysid``, ``compid``) heard at ``where`` stands (rule 2):
        ``"bound"`` (its own address; a first frame that ``announces`` the component, its
        HEARTBEAT, binds it), ``"moved"`` (it moves here now; only if ``may_move``: the daemon
        says so of a vehicle it counts as gone), ``"refused"`` (a second address) or
        ``"unbound"`` (the component is bound nowhere and this frame cannot bind it)."""
        trust = self._trust(sysid)
        binding = trust.bindings.get(compid)
        autopilot = trust.bindings.get(AUTOPILOT_COMPONENT_ID)
        via_autopilot = compid != AUTOPILOT_COMPONENT_ID and (
            autopilot is not None and autopilot.where == where
        )
        if binding is None:
            if announces or via_autopilot:
                self._bind(trust, compid, where, now_s)
                return "bound"
            self.unbound(sysid, where)
            return "unbound"
        if binding.where == where:
            binding.heard_s = now_s
            return "bound"
        silent_s = now_s - binding.heard_s
        # a component heard through its autopilot is there, whoever claimed it elsewhere first
        if via_autopilot or (announces and may_move and silent_s >= self.limits.move_after_s):
            self._bind(trust, compid, where, now_s)
            self.counts.address_moves += 1
            why = (
                "heard through its autopilot"
                if via_autopilot
                else f"its old address silent {silent_s:.1f} s"
            )
            self.notices.append(
                f"vehicle {sysid} component {compid} moved to {_place(where)} "
                f"from {_place(binding.where)} ({why})"
            )
            return "moved"
        self.counts.second_address += 1
        self._refused(sysid, compid, binding, where)
        return "refused"

    def _refused(
        self, sysid: VehicleKey, compid: int, binding: _Binding, where: tuple[int, Any]
    ) -> None:
        """Count a second address of a bound component once, and say it in one line (the
        first ``_CONFLICTS_SAID`` of them; a spoofer changing ports cannot flood the log)."""
        key = (sysid, compid, where)
        if key in self._conflicts or len(self._conflicts) >= _CONFLICTS_REMEMBERED:
            return
        self._conflicts.add(key)
        self.counts.address_conflicts += 1
        if self.counts.address_conflicts <= _CONFLICTS_SAID:
            part = "" if compid == AUTOPILOT_COMPONENT_ID else f" component {compid}"
            who = f"vehicle {sysid}{part}"
            self.notices.append(
                f"{who}: refused {_place(where)}, a second sender with its system id (the "
                f"vehicle is bound to {_place(binding.where)}); nothing is sent there: find that "
                f"sender, or sign the link"
            )
        elif self.counts.address_conflicts == _CONFLICTS_SAID + 1:
            self.notices.append(
                "more addresses claim bound system ids: refused and counted "
                "(address_conflicts), not said"
            )

    def unbound(self, sysid: VehicleKey, where: tuple[int, Any]) -> None:
        """A frame of (``sysid``, bound to nothing) from ``where``: dropped, and counted while
        ``where`` is not bound to ``sysid`` (``_bind`` takes back the count of a vehicle's own
        frames before its first HEARTBEAT: ``unbound`` is what senders that never became a
        vehicle sent)."""
        self.counts.unbound += 1
        key = (sysid, where)
        if key in self._unbound or len(self._unbound) < _SENDERS_REMEMBERED:
            self._unbound[key] = self._unbound.get(key, 0) + 1

    def _bind(self, trust: VehicleTrust, compid: int, where: tuple[int, Any], now_s: float) -> None:
        trust.bindings[compid] = _Binding(where, now_s)
        self.counts.unbound -= self._unbound.pop((trust.system_id, where), 0)

    def _trust(self, sysid: VehicleKey) -> VehicleTrust:
        trust = self.vehicles.get(sysid)
        if trust is None:
            trust = self.vehicles[sysid] = VehicleTrust(system_id=sysid)
        return trust

    # ------------------------------------------------------------------ content

    def admit(self, sysid: VehicleKey, msg: mavlink.MAVLink_message, now_s: float) -> bool:
        """True if ``msg`` (already from the vehicle's bound address) may change its state."""
        trust = self._trust(sysid)
        check = _CHECKS.get(msg.get_type())
        return True if check is None else check(self, trust, msg, now_s)

    def _reject(self, rule: str) -> bool:
        setattr(self.counts, rule, getattr(self.counts, rule) + 1)
        return False

    def _heartbeat(self, trust: VehicleTrust, msg: Any, now_s: float) -> bool:
        if not 0 <= msg.system_status <= _MAX_MAV_STATE:
            return self._reject("out_of_range")
        if msg.get_srcComponent() != 1:
            return True
        if trust.vehicle_type is None:
            trust.vehicle_type = msg.type
        elif msg.type != trust.vehicle_type:
            return self._reject("out_of_range")  # an airframe does not change its kind
        return True

    def _fields_ok(self, lat_e7: int, lon_e7: int, alt_mm: int) -> bool:
        low, high = self.limits.altitude_range_m
        return on_earth(lat_e7, lon_e7) and low <= alt_mm * 1e-3 <= high

    def _position(self, trust: VehicleTrust, msg: Any, now_s: float) -> bool:
        lim = self.limits
        speed = math.sqrt(msg.vx**2 + msg.vy**2 + msg.vz**2) * 1e-2
        heading_ok = msg.hdg == 65535 or 0 <= msg.hdg < 36000
        if not (self._fields_ok(msg.lat, msg.lon, msg.relative_alt) and heading_ok):
            return self._reject("out_of_range")
        if speed > lim.max_ground_speed_mps:
            return self._reject("out_of_range")
        if trust.fix is None and abs(msg.lat) < _NO_POSITION_E7 and abs(msg.lon) < _NO_POSITION_E7:
            return self._reject("no_position")  # the placeholder before the first position
        new = _Fix(int(msg.time_boot_ms), msg.lat * 1e-7, msg.lon * 1e-7, now_s)
        if self._past_grant(new):
            trust.past_grant += 1  # lockstep: a clock that runs free (LockstepClock says so)
            return self._reject("time_jump")
        trust.past_grant = 0
        fix = trust.fix
        if fix is None:
            trust.fix = trust.base = new
            return True
        verdict = self._follows(trust, fix, new, now_s)
        if verdict is None:
            trust.fix, trust.candidates = new, []
            return True
        # not the believed time base: a new one if it is the only one left (module docstring)
        if trust.candidates and self._follows(trust, trust.candidates[-1], new, now_s, rebase=True):
            trust.candidates = []
        trust.candidates.append(new)
        first = trust.candidates[0]
        if (
            len(trust.candidates) >= lim.rebase_frames
            and now_s - first.wall_s >= lim.rebase_after_s
            and now_s - fix.wall_s >= lim.rebase_after_s
            and not self._past_grant(new)
        ):
            self.counts.clock_rebases += 1
            self.notices.append(_rebase_notice(trust.system_id, fix, first))
            trust.fix = trust.base = new
            trust.candidates = []
            return True
        return self._reject(verdict)

    def _follows(
        self, trust: VehicleTrust, old: _Fix, new: _Fix, now_s: float, rebase: bool = False
    ) -> str | None:
        """None if ``new`` can follow ``old`` on one vehicle clock; else the rule it breaks
        (with ``rebase``: any non-None result means the candidate chain breaks)."""
        dt_ms = new.time_ms - old.time_ms
        if dt_ms < 0:
            return "stale_positions"
        if dt_ms > self._clock_allowance_ms(trust, old, now_s) and not rebase:
            return "time_jump"
        if not self._reachable(old, new.lat_deg, new.lon_deg, dt_ms):
            return "too_fast"
        return None

    def _past_grant(self, fix: _Fix) -> bool:
        """Lockstep: stamped after the horizon granted to the vehicles (impossible when the
        simulator holds there; before the first grant nothing is known)."""
        return (
            self.limits.lockstep and self.granted_ms is not None and fix.time_ms > self.granted_ms
        )

    def running_free(self, sysid: VehicleKey) -> bool:
        """Lockstep: vehicle ``sysid`` has reported ``rebase_frames`` positions in a row past the
        granted horizon, from its own address: its simulator does not hold (lockstep released)."""
        trust = self.vehicles.get(sysid)
        return trust is not None and trust.past_grant >= self.limits.rebase_frames

    def _clock_allowance_ms(self, trust: VehicleTrust, old: _Fix, now_s: float) -> float:
        """How far the vehicle's clock can have run since ``old`` was believed: in lockstep to
        the granted horizon; else the wall time since x its clock rate (the declared
        ``time_scale`` or, if faster, the rate measured over its time base: a SITL run at a
        --speedup the daemon was not told of is not a spoofer), with slack. Before a rate could
        be measured (``rebase_after_s`` of its time base) ``UNMEASURED_RATE``."""
        lim = self.limits
        if lim.lockstep and self.granted_ms is not None:
            return self.granted_ms - old.time_ms
        base, fix = trust.base, trust.fix
        if base is None or fix is None or fix.wall_s - base.wall_s < lim.rebase_after_s:
            measured = UNMEASURED_RATE  # its first second: any speedup a simulator runs at
        else:
            measured = (fix.time_ms - base.time_ms) / 1e3 / (fix.wall_s - base.wall_s)
        allowed = (
            max(0.0, now_s - old.wall_s)
            * max(lim.time_scale, measured, 1.0)
            * lim.clock_slack
            * 1e3
            + lim.clock_slack_ms
        )
        if self.granted_ms is not None:
            allowed = max(allowed, self.granted_ms - old.time_ms)
        return allowed

    def _reachable(self, old: _Fix, lat_deg: float, lon_deg: float, dt_ms: float) -> bool:
        reach = self.limits.max_ground_speed_mps * abs(dt_ms) * 1e-3 + self.limits.position_slack_m
        return ground_distance_m(old.lat_deg, old.lon_deg, lat_deg, lon_deg) <= reach

    def _home(self, trust: VehicleTrust, msg: Any, now_s: float) -> bool:
        if not self._fields_ok(msg.latitude, msg.longitude, 0) or not (-1e6 <= msg.altitude <= 1e7):
            return self._reject("out_of_range")
        return True

    def _look(self, trust: VehicleTrust, msg: Any, now_s: float) -> bool:
        """A sensor look: on Earth, and where the vehicle can have been at its time."""
        if not on_earth(msg.lat, msg.lon):
            return self._reject("out_of_range")
        fix = trust.fix
        if fix is None:
            return True
        dt_ms = int(msg.time_boot_ms) - fix.time_ms
        if dt_ms < -self.limits.oldest_look_ms:
            return self._reject("stale_positions")  # a replay of a look long past
        if dt_ms > self._clock_allowance_ms(trust, fix, now_s):
            return self._reject("time_jump")
        if not self._reachable(fix, msg.lat * 1e-7, msg.lon * 1e-7, dt_ms):
            return self._reject("too_fast")
        return True


_CHECKS = {
    "HEARTBEAT": PlausibilityFilter._heartbeat,
    "GLOBAL_POSITION_INT": PlausibilityFilter._position,
    "HOME_POSITION": PlausibilityFilter._home,
    "CAMERA_IMAGE_CAPTURED": PlausibilityFilter._look,
}
