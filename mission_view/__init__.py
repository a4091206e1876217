"""The mission view: a browser page that shows a mission as it flies (the live view, served by
``swarmplan daemon`` and ``swarmplan demo``) or after it (``swarmplan view RESULT_DIR``, a replay
with a time slider), with what the swarm believes as a heat layer. See docs/view.md."""
