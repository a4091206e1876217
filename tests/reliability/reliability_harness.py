"""What the reliability tests share beyond the loopback helpers (tests/loopback.py: free ports,
``python -m swarmplan`` subprocesses and their clean shutdown): a fixed signing key and the
simulator's summary line."""

from __future__ import annotations

import json
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
