"""What a simulator started by a command (``swarmplan demo``, onboard or not) said in its log."""

from __future__ import annotations

import json
from pathlib import Path


def simulator_summary(path: Path) -> dict | None:
    """The simulator's JSON summary (the last JSON line of its log), if it wrote one."""
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        if line.startswith("{"):
            try:
                return json.loads(line)
            except ValueError:
                return None
    return None
