"""A change of mode drops a speed commanded with DO_CHANGE_SPEED, as ArduPlane's Mode::enter
does (new_airspeed_cm = -1); the same mode asked again keeps it. Over the simulator's MAVLink
endpoint on loopback, as a ground station sees it (VFR_HUD airspeed)."""

from __future__ import annotations

import pytest
from sim_harness import take_off

from sim_gateway.flight_modes import GUIDED, RTL

DO_CHANGE_SPEED, DO_SET_MODE = 178, 176


@pytest.mark.timeout(60)
def test_a_leg_flown_at_150_ms_comes_home_in_rtl_at_cruise(gcs, sim_factory):
    sim_factory(speedup=20.0)
    take_off(gcs)
    assert gcs.command_long(1, DO_SET_MODE, 1, GUIDED).result == 0
    assert gcs.command_long(1, DO_CHANGE_SPEED, 0, 150).result == 0
    fast = gcs.wait("VFR_HUD", 1, 20, cond=lambda m: m.airspeed > 145)
    assert fast is not None, "the plane never reached the commanded 150 m/s"
    # GUIDED again (a DO_SET_MODE to the mode it is in) keeps the commanded speed
    assert gcs.command_long(1, DO_SET_MODE, 1, GUIDED).result == 0
    gcs.drain()
    assert gcs.wait("VFR_HUD", 1, 5).airspeed > 145
    # RTL: back to AIRSPEED_CRUISE (100 m/s in paper-2uav)
    assert gcs.command_long(1, DO_SET_MODE, 1, RTL).result == 0
    cruise = gcs.wait("VFR_HUD", 1, 20, cond=lambda m: m.airspeed < 101)
    assert cruise is not None and cruise.airspeed > 99, "RTL kept the leg's 150 m/s"
