"""The flight home: who gets RTL at every way out (``rtl_at_exit``), the way home clear of
threats (``around_threats``), planes kept apart on their ways home (``kept_apart``, with
``homeward``, ``homeward_flights`` and ``home_circles``), and the watch of the flight home after
the mission (``flight_home``). May import ``safety``, ``vehicles`` and ``results``."""
