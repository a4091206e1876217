"""The mission's phases and the daemon that runs them: discovery, readiness, fence, arming and
take-off (``launch``), the take back of planes in the air after a restart
(``resume_takeback``), the decision loop (``decision_step``) paced by the vehicles' clock or in
lockstep (``pacing``, ``lockstep_clock``, ``keeping_up``), the scenario as the daemon's planner
plans it (``flown_planning``), the live view's feed (``view_feed``), and ``MissionDaemon``
(``daemon``). May import every other sub-package of ``mavlink_bridge``."""
