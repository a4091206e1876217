"""The vehicles as the daemon knows them: each one's state from its messages
(``vehicle_state``), what of it to believe (``telemetry_plausibility``), its links and discovery
(``swarm_link``, ``discovery``), its airframe and how it flies (``airframe``,
``flight_prediction``), readiness and arming (``readiness``), its GCS failsafe
(``gcs_failsafe``), commands with retry (``guided_commands``), the fence upload
(``fence_upload``), its sensor looks (``sensor_looks``) and its loss and return
(``vehicle_loss``). May import ``results``."""
