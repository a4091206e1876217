"""Which telemetry a simulated vehicle streams and when: the default rates, ArduPilot's stream
groups (:data:`DATA_STREAMS`), each vehicle's :class:`StreamSchedule`, and the
:class:`FleetSnapshot` of one telemetry frame that the messages are built from
(``sim_gateway/telemetry.py`` builds them).

Rates count wall-clock seconds (at a 50x speedup a 10 Hz position stream is one message per 5 s
of simulated flight): a ground station or daemon receives at a wall-clock rate, and receiving is
its bottleneck. MAV_CMD_SET_MESSAGE_INTERVAL and REQUEST_DATA_STREAM change them per vehicle, as
on ArduPilot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink

#: Default rates in Hz (wall clock). HEARTBEAT is always 1 Hz.
DEFAULT_RATES_HZ = {
    "HEARTBEAT": 1.0,
    "SYS_STATUS": 1.0,
    "GLOBAL_POSITION_INT": 10.0,
    "ATTITUDE": 10.0,
    "VFR_HUD": 4.0,
    "GPS_RAW_INT": 2.0,
    "EXTENDED_SYS_STATE": 1.0,
    "MISSION_CURRENT": 1.0,
    "HOME_POSITION": 0.2,
    "SYSTEM_TIME": 0.5,
}
MAX_RATE_HZ = 50.0

#: REQUEST_DATA_STREAM groups -> messages (ArduPilot's stream groups, restricted to ours).
DATA_STREAMS = {
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYS_STATUS", "GPS_RAW_INT", "MISSION_CURRENT"),
    mavlink.MAV_DATA_STREAM_POSITION: ("GLOBAL_POSITION_INT",),
    mavlink.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    mavlink.MAV_DATA_STREAM_EXTRA2: ("VFR_HUD",),
    mavlink.MAV_DATA_STREAM_EXTRA3: ("EXTENDED_SYS_STATE", "SYSTEM_TIME"),
}
DATA_STREAMS[mavlink.MAV_DATA_STREAM_ALL] = tuple(
    m for group in DATA_STREAMS.values() for m in group
)

MESSAGE_IDS = {name: getattr(mavlink, f"MAVLINK_MSG_ID_{name}") for name in DEFAULT_RATES_HZ}
NAMES_BY_ID = {v: k for k, v in MESSAGE_IDS.items()}


@dataclass
class StreamSchedule:
    """Interval (s) and next due wall time of each stream of one vehicle."""

    interval_s: dict[str, float | None] = field(
        default_factory=lambda: {k: 1.0 / v for k, v in DEFAULT_RATES_HZ.items()}
    )
    next_due_s: dict[str, float] = field(default_factory=dict)

    def set_rate_hz(self, name: str, rate_hz: float | None) -> None:
        """Set a stream's rate; None or <= 0 stops it."""
        if rate_hz is None or rate_hz <= 0:
            self.interval_s[name] = None
        else:
            self.interval_s[name] = 1.0 / min(rate_hz, MAX_RATE_HZ)
        self.next_due_s.pop(name, None)

    def reset_default(self, name: str) -> None:
        self.set_rate_hz(name, DEFAULT_RATES_HZ[name])

    def due(self, now_s: float) -> list[str]:
        """Streams due at ``now_s``, each rescheduled one interval on (no burst after a stall)."""
        out = []
        for name, interval in self.interval_s.items():
            if interval is None:
                continue
            nxt = self.next_due_s.get(name)
            if nxt is None or now_s >= nxt:
                out.append(name)
                base = now_s if nxt is None or now_s - nxt > interval else nxt
                self.next_due_s[name] = base + interval
        return out


@dataclass
class FleetSnapshot:
    """Per-vehicle values computed once per telemetry frame for the whole fleet."""

    lat_e7: list[int]
    lon_e7: list[int]
    home_lat_e7: list[int]
    home_lon_e7: list[int]
    time_boot_ms: int
    time_unix_us: int
    range_remaining_pct: list[int]
