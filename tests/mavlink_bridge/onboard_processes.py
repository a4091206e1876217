"""The processes ``swarmplan demo --onboard`` leaves running in sessions of their own (the
simulator and the nodes): their pids as the coordinator says them, and a stop by pid (only
ours)."""

from __future__ import annotations

import os
import re
import signal
import time
from pathlib import Path


def onboard_pids(log: Path, coordinator, timeout_s: float = 120.0) -> list[int]:
    """The simulator's and the nodes' pids, as the coordinator says them."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and coordinator.poll() is None:
        text = log.read_text(errors="replace") if log.exists() else ""
        sim = re.search(r"simulator pid (\d+)", text)
        nodes = re.search(r"node pids ([\d ]+)", text)
        if sim and nodes:
            return [int(sim.group(1)), *map(int, nodes.group(1).split())]
        time.sleep(0.2)
    raise AssertionError(f"the coordinator never said its pids: {log.read_text()[-2000:]}")


def is_running(pid: int) -> bool:
    try:
        return b"swarmplan" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False


def end_processes(pids: list[int]) -> None:
    """Stop what the coordinator started and left running (by pid, only ours)."""
    for pid in pids:
        if is_running(pid):
            os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + 10
    while any(is_running(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.2)
    for pid in pids:
        if is_running(pid):
            os.kill(pid, signal.SIGKILL)
