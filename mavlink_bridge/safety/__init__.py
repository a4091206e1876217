"""Safety, judged independently of the planner: every guided target checked against the area,
the threats, separation and range at the cell level (``safety_envelope``) and along the path a
plane will really fly (``flight_envelope``, with ``flight_candidates``, ``flight_settling`` and
``lossy_link_paths``), and safety measured along every flown track (``track_audit``). May
import ``vehicles`` and ``results``."""
