"""The MAVLink both sides speak: the simulator (``sim_gateway``) and the daemon
(``mavlink_bridge``) stand on it side by side. The dialect and the ids the project uses
(``protocol``), transport endpoints and the per-vehicle link (``links``), MAVLink 2 signing
(``signing``), the telemetry log (``tlog``) and the encoding of a sensor look in standard
messages (``looks``). Imports pymavlink, the standard library and ``planner.errors`` only."""
