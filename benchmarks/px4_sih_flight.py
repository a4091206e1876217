"""What PX4 SITL's SIH airplane really flies: its top airspeed and its turn.

One PX4 SIH instance (tests/sitl/px4_harness.py, ``PX4_SITL``) is armed, takes off to 60 m,
and is sent 3 km north (DO_REPOSITION, AUTO.LOITER) at each asked airspeed (DO_CHANGE_SPEED);
the mean VFR_HUD airspeed, ground speed and throttle are logged over level flight only
(|climb| < 0.5 m/s, course within 10 deg of the leg, after a settling time). Then it is sent
back south (a 180 deg turn): the largest bank (ATTITUDE roll) and the turn radius
(ground speed / course rate) while turning, and the loiter radius flown at the far point::

    PX4_SITL=../shared/sitl/px4 python benchmarks/px4_sih_flight.py [--speedup 5]

Prints one line per measurement and a JSON summary on the last line.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "sitl"))

from px4_harness import Px4Swarm, px4_root_from_env, skip_reason  # noqa: E402
from pymavlink import mavutil  # noqa: E402
from sitl_harness import Home  # noqa: E402

from mavlink_bridge.vehicles.param_encoding import decode_param  # noqa: E402

M = mavutil.mavlink
HOME = Home(47.3977, 8.5456, 488.0, 0.0)
PARAMS = ("FW_AIRSPD_MIN", "FW_AIRSPD_TRIM", "FW_AIRSPD_MAX", "FW_R_LIM", "NAV_LOITER_RAD",
          "FW_THR_MAX", "FW_THR_TRIM", "SIH_T_MAX", "SYS_AUTOSTART")  # fmt: skip


class Probe:
    """The GCS link of one instance, its latest messages, and sim-time pacing."""

    def __init__(self, url: str, speedup: float) -> None:
        self.m = mavutil.mavlink_connection(url, source_system=255)
        self.speedup = speedup
        self.last: dict[str, object] = {}

    def pump(self, sim_s: float, until=None, on=None) -> bool:
        end = time.monotonic() + sim_s / self.speedup
        while time.monotonic() < end:
            self.m.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            msg = self.m.recv_match(blocking=True, timeout=0.05)
            while msg is not None:
                self.last[msg.get_type()] = msg
                if on is not None:
                    on(msg)
                msg = self.m.recv_match(blocking=False)
            if until is not None and until():
                return True
        return False

    def command(self, cmd: int, *params: float) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        self.last.pop("COMMAND_ACK", None)
        self.m.mav.command_long_send(1, 1, cmd, 0, *p)
        self.pump(10, until=lambda: "COMMAND_ACK" in self.last)
        ack = self.last.get("COMMAND_ACK")
        return -1 if ack is None else ack.result

    def reposition(self, north_m: float, alt_m: float) -> int:
        lat = HOME.lat_deg + north_m / 111_320.0
        self.last.pop("COMMAND_ACK", None)
        self.m.mav.command_int_send(
            1, 1, M.MAV_FRAME_GLOBAL, M.MAV_CMD_DO_REPOSITION, 0, 0, -1, 1, 0, math.nan,
            int(lat * 1e7), int(HOME.lon_deg * 1e7), HOME.alt_m + alt_m,
        )  # fmt: skip
        self.pump(10, until=lambda: "COMMAND_ACK" in self.last)
        return getattr(self.last.get("COMMAND_ACK"), "result", -1)

    def north_m(self) -> float:
        pos = self.last["GLOBAL_POSITION_INT"]
        return (pos.lat * 1e-7 - HOME.lat_deg) * 111_320.0


def level_means(p: Probe, course_deg: float, sim_s: float) -> dict[str, float]:
    """Mean airspeed, ground speed, throttle over level straight flight on ``course_deg``."""
    rows = []

    def on(msg) -> None:
        on_course = abs((getattr(msg, "heading", 0) - course_deg + 180) % 360 - 180) < 10
        if msg.get_type() == "VFR_HUD" and abs(msg.climb) < 0.5 and on_course:
            rows.append((msg.airspeed, msg.groundspeed, msg.throttle))

    p.pump(sim_s, on=on)
    if not rows:
        return {"samples": 0}
    n = len(rows)
    return {"airspeed": round(sum(r[0] for r in rows) / n, 2),
            "groundspeed": round(sum(r[1] for r in rows) / n, 2),
            "throttle": round(sum(r[2] for r in rows) / n, 1), "samples": n}  # fmt: skip


def turn_figures(p: Probe, sim_s: float) -> dict[str, float]:
    """Largest bank and tightest radius (ground speed / course rate) over ``sim_s``."""
    track: list[tuple[float, float, float]] = []
    rolls: list[float] = []

    def on(msg) -> None:
        if msg.get_type() == "ATTITUDE":
            rolls.append(abs(math.degrees(msg.roll)))
        if msg.get_type() == "GLOBAL_POSITION_INT":
            speed = math.hypot(msg.vx, msg.vy) / 100
            track.append((msg.time_boot_ms / 1e3, math.atan2(msg.vy, msg.vx), speed))

    p.pump(sim_s, on=on)
    window = max(1, len(track) * 2 // max(1, round(sim_s)))  # ~2 s of position reports
    radii = []
    for (t0, c0, _), (t1, c1, v1) in zip(track, track[window:], strict=False):
        rate = abs((c1 - c0 + math.pi) % (2 * math.pi) - math.pi) / max(t1 - t0, 1e-3)
        if rate > 0.02:
            radii.append(v1 / rate)
    return {"max_bank_deg": round(max(rolls, default=0), 1),
            "min_radius_m": round(min(radii, default=math.nan), 0)}  # fmt: skip


def loiter_radius_m(p: Probe, north_m: float, sim_s: float) -> float:
    """Mean distance from the loiter point (``north_m`` north of home) over ``sim_s``."""
    lat0 = HOME.lat_deg + north_m / 111_320.0
    metres_per_deg_lon = 111_320.0 * math.cos(math.radians(lat0))
    dists = []

    def on(msg) -> None:
        if msg.get_type() == "GLOBAL_POSITION_INT":
            dn = (msg.lat * 1e-7 - lat0) * 111_320.0
            de = (msg.lon * 1e-7 - HOME.lon_deg) * metres_per_deg_lon
            dists.append(math.hypot(dn, de))

    p.pump(sim_s, on=on)
    return round(sum(dists) / max(len(dists), 1), 1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--speedup", type=float, default=5.0)
    parser.add_argument("--speeds", default="12,15,20", help="airspeeds asked, m/s")
    args = parser.parse_args()
    root = px4_root_from_env()
    if root is None:
        print(skip_reason(), file=sys.stderr)
        return 2
    out: dict[str, object] = {"speedup": args.speedup, "load": os.getloadavg()[0]}
    with Px4Swarm(root, [HOME], speedup=args.speedup) as swarm:
        p = Probe(swarm.vehicles[0].master, args.speedup)
        p.pump(60, until=lambda: "HEARTBEAT" in p.last)
        params = {}
        for name in PARAMS:
            p.m.mav.param_request_read_send(1, 1, name.encode(), -1)
            p.pump(3, until=lambda n=name: getattr(p.last.get("PARAM_VALUE"), "param_id", "") == n)
            value = p.last.get("PARAM_VALUE")
            if value is not None and value.param_id == name:
                number = decode_param(M.MAV_AUTOPILOT_PX4, value.param_value, value.param_type)
                params[name] = round(number, 2)
        out["params"] = params
        print("params", params, flush=True)
        prearm = M.MAV_SYS_STATUS_PREARM_CHECK
        p.pump(120, until=lambda: p.last.get("SYS_STATUS") is not None
               and p.last["SYS_STATUS"].onboard_control_sensors_health & prearm)  # fmt: skip
        p.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        p.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, HOME.alt_m + 70)
        p.pump(120, until=lambda: p.last["GLOBAL_POSITION_INT"].relative_alt > 55_000)
        leg = 3000.0
        p.reposition(leg, 60)
        p.pump(20)
        for speed in (float(s) for s in args.speeds.split(",")):
            p.command(M.MAV_CMD_DO_CHANGE_SPEED, 0, speed, -1)
            p.pump(15)  # settle
            out[f"asked_{speed:g}"] = level_means(p, 0.0, 25)
            print(f"asked {speed:g} m/s:", out[f"asked_{speed:g}"], flush=True)
        p.command(M.MAV_CMD_DO_CHANGE_SPEED, 0, 20, -1)
        back = p.north_m() - 1500
        p.reposition(back, 60)  # turn about at the fastest it flies
        out["turn_about"] = turn_figures(p, 30)
        print("turn about:", out["turn_about"], flush=True)
        p.pump(200, until=lambda: abs(p.north_m() - back) < 150)
        p.pump(20)
        out["loiter"] = turn_figures(p, 60)
        out["loiter"]["mean_radius_m"] = loiter_radius_m(p, back, 60)
        print("loiter:", out["loiter"], flush=True)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
