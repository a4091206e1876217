"""What the reliability tests share beyond the loopback helpers (tests/loopback.py: free ports,
``python -m swarmplan`` subprocesses and their clean shutdown): a fixed signing key and the
simulator's summary line."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

KEY_HEX = "5a" * 16 + "c3" * 16  # a fixed test key (64 hex characters)


def last_json(log: Path) -> dict | None:
    """The last line of ``log`` that is a JSON object (the simulator's summary), if any."""
    for line in reversed(log.read_text(errors="replace").splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except ValueError:
                continue
    return None


def checkpoint_step(path: Path) -> int:
    """The step of the mission's checkpoint at ``path`` (signed with ``KEY_HEX``), -1 if none."""
    from mavlink_bridge.results.checkpoint import CheckpointError, read_checkpoint

    try:
        return read_checkpoint(path, bytes.fromhex(KEY_HEX)).step
    except CheckpointError:
        return -1


def wait_until(predicate, timeout_s: float, procs: list[subprocess.Popen]) -> bool:
    """``predicate()`` true within ``timeout_s``; once one of ``procs`` ends, its last word."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        if any(p.poll() is not None for p in procs):
            return predicate()
        time.sleep(0.02)
    return False
