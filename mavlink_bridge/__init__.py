"""The planner daemon: flies a swarm of MAVLink autopilots (ArduPlane / PX4 SITL, hardware or the
project's simulator) with a swarm planner, and exports the plan as waypoint files.

Its sub-packages, from the top down (each imports only those below it; ``lint-imports`` checks):

- ``mission``: the mission's phases (launch, the decision loop and its pacing, the take back
  after a restart) and ``MissionDaemon`` that runs them;
- ``way_home``: the flight home at every way out, clear of threats and kept apart;
- ``safety``: every guided target judged independently of the planner (cell and flight-path
  envelopes) and the safety measured along the flown tracks;
- ``vehicles``: what the daemon knows of each vehicle and the commands it sends one;
- ``results``: what a mission tells the world (result, link events) and its checkpoints;
- ``export``: waypoint and map files for ground stations.

It stands on ``mavlink_wire`` (the MAVLink both sides speak) and ``planner``; it meets the
simulator only over MAVLink and never imports ``sim_gateway``. See docs/architecture.md.
"""
