"""Return to launch: on command, and by itself when the range (L_max, the "battery") is used up."""

from __future__ import annotations


def test_rtl_command_and_range_used_up_return_to_launch(gcs):
    """MAV_CMD_NAV_RETURN_TO_LAUNCH switches to RTL; a vehicle whose range (L_max) is used up
    says so and returns by itself (battery failsafe), its SYS_STATUS battery at 0 %."""
    from sim_harness import RunningSim

    from planner.scenario import load_scenario
    from sim_gateway.simulator import SimOptions, Simulator

    sim = Simulator(
        load_scenario("paper-2uav"),
        SimOptions(gcs_port=gcs.port, airborne=True, speedup=50.0, boot_s=0.0),
    )
    # vehicle 1 has 8 km of range left (80 s of flight at 100 m/s, 1.6 s of wall time at 50x);
    # vehicle 2 has all 100 km (20 s of wall time), so only the command can send it home
    sim.max_range_m = 100_000.0
    sim.fleet.distance_flown_m[0] = 92_000.0
    running = RunningSim(sim)
    try:
        gcs.ensure_peer()
        gcs.heartbeat()
        text = gcs.wait("STATUSTEXT", 1, 10, cond=lambda m: "Battery 1 is critical" in m.text)
        assert text is not None, "no range failsafe"
        assert gcs.wait("HEARTBEAT", 1, 5, cond=lambda m: m.custom_mode == 11)
        assert gcs.wait("SYS_STATUS", 1, 5, cond=lambda m: m.battery_remaining == 0)
        gcs.heartbeat()
        ack = gcs.command_long(2, 20)
        assert ack is not None and ack.result == 0
        assert gcs.wait("HEARTBEAT", 2, 5, cond=lambda m: m.custom_mode == 11)
        assert not sim.vehicles[1].range_exhausted  # RTL by command, not by battery failsafe
    finally:
        running.close()
