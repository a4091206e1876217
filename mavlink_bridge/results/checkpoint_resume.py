"""Resuming from a checkpoint: the restored planner takes the parts this code builds for the
mission (``DERIVED``), the daemon's counters come back, and the outage is no leg. The file and
its checks: ``checkpoint.py``."""

from __future__ import annotations

from typing import Any

from mavlink_bridge.results.checkpoint import DAEMON_STATE, DERIVED, Checkpoint


def _split(path: str) -> tuple[list[str], str]:
    *owners, name = path.split(".")
    return owners, name


def with_derived(restored: Any, fresh: Any) -> None:
    """Put the :data:`DERIVED` attributes of ``fresh`` (built for this mission) into
    ``restored``."""
    for path in DERIVED:
        owners, name = _split(path)
        src, dst = fresh, restored
        for owner in owners:
            src, dst = getattr(src, owner, None), getattr(dst, owner, None)
        if hasattr(src, name) and dst is not None:
            setattr(dst, name, getattr(src, name))


def resume_loop_state(account: Any, checkpoint: Checkpoint, fresh_planner: Any) -> dict[str, Any]:
    """The decision loop's variables from ``checkpoint``, with the mission's counters restored
    into ``account``.

    ``checkpoint``: from :func:`load_for_mission` (checked against the mission);
    ``fresh_planner``: the planner this code builds for the mission, whose :data:`DERIVED`
    parts the restored one takes."""
    with_derived(checkpoint.loop["planner"], fresh_planner)
    hand_over = getattr(fresh_planner, "hand_over", None)
    if hand_over is not None:  # a planner node's: its link and clock (onboard_planner.py)
        hand_over(checkpoint.loop["planner"])
    break_measured_legs(checkpoint.loop["recorder"])
    for name in DAEMON_STATE:
        setattr(account, name, checkpoint.daemon[name])
    return checkpoint.loop


def break_measured_legs(recorder: Any) -> None:
    """The outage is not a leg: while the daemon was down the autopilots' failsafe flew the
    vehicles (loitering, circling), so the straight chord from the last position before the
    crash to the first one after it, and the turns at its ends, say nothing about the
    planner's path. The recorder starts each UAV's leg chain afresh after a restart (threat
    and separation are still judged at every recorded position; the distance flown during the
    outage is not in the recorder's total, while the safety envelope's range account, between
    measured cells, includes it)."""
    recorder.break_legs()
