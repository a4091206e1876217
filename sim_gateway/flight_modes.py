"""ArduPlane flight modes: their numbers (HEARTBEAT custom_mode) and names.

The numbers are ArduPlane's ``Mode::Number``; the simulator flies the ones in
:data:`SUPPORTED_MODES` (FBWA / FBWB / CRUISE have no pilot here and hold course and altitude).
"""

from __future__ import annotations

MANUAL = 0
CIRCLE = 1
STABILIZE = 2
FBWA = 5
FBWB = 6
CRUISE = 7
AUTO = 10
RTL = 11
LOITER = 12
TAKEOFF = 13
GUIDED = 15

MODE_NAMES = {
    MANUAL: "MANUAL",
    CIRCLE: "CIRCLE",
    STABILIZE: "STABILIZE",
    FBWA: "FBWA",
    FBWB: "FBWB",
    CRUISE: "CRUISE",
    AUTO: "AUTO",
    RTL: "RTL",
    LOITER: "LOITER",
    TAKEOFF: "TAKEOFF",
    GUIDED: "GUIDED",
}
SUPPORTED_MODES = frozenset(MODE_NAMES)
HOLD_COURSE_MODES = frozenset({MANUAL, STABILIZE, FBWA, FBWB, CRUISE})


def mode_name(mode: int) -> str:
    return MODE_NAMES.get(mode, f"MODE{mode}")
