"""The planner daemon: flies a swarm of MAVLink autopilots (ArduPlane / PX4 SITL, hardware or the
project's simulator) with the HAPF-ACO planner, and exports the plan as waypoint files.

It meets the simulator only over MAVLink and never imports ``sim_gateway``. See docs/daemon.md.
"""
