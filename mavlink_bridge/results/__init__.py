"""What a mission tells the world: the per-step record and link events, the result and its
account (``mission_result``), and the checkpoint a restarted daemon resumes from
(``checkpoint``, stored as data by ``checkpoint_codec``, checked by ``checkpoint_layout``).
Imports no other sub-package of ``mavlink_bridge``."""
