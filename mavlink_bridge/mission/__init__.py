"""The mission's phases and the daemon that runs them. Every phase owns its state and takes the
mission's context (``context``: the link, the vehicles, the lockstep clock, the airframe in
force, the counters, ``send`` and ``say``; the options in ``options``): the launch (``launch``:
discovery, readiness, fence, arming, take-off), the take back of planes in the air after a
restart (``resume_takeback``), the decision loop (``decision_loop``, its step's stages in
``decision_step`` and its state in ``loop_state``) paced by the vehicles' clock or in lockstep
(``pacing``, which also measures each step's lateness, ``lockstep_clock``, ``keeping_up``), the
scenario as the daemon's planner plans it from plain inputs (``flown_planning``), the live
view's feed (``view_feed``), and ``MissionDaemon`` (``daemon``), which builds and runs them.
May import every other sub-package of ``mavlink_bridge``."""
