"""Processes for the reliability tests: the simulator and the daemon as real subprocesses
(``python -m swarmplan sim|daemon``), free loopback ports, and clean shutdown.

Every process started here is registered and ended by :func:`stop` (SIGTERM, then SIGKILL), so
a failing test never leaves one behind.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
KEY_HEX = "5a" * 16 + "c3" * 16  # a fixed test key (64 hex characters)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def env(**extra: str) -> dict[str, str]:
    out = dict(os.environ, PYTHONPATH=str(REPO), MAVLINK20="1")
    out.pop("SWARMPLAN_SIGNING_KEY", None)
    out.update(extra)
    return out


def start_swarmplan(
    args: list[str], log: Path, environ: dict[str, str] | None = None
) -> subprocess.Popen:
    """``python -m swarmplan ARGS`` with stdout and stderr into ``log``."""
    with open(log, "ab") as sink:
        return subprocess.Popen(
            [sys.executable, "-m", "swarmplan", *args],
            stdout=sink,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=environ or env(),
            cwd=REPO,
        )


def stop(proc: subprocess.Popen, timeout_s: float = 5.0) -> int | None:
    """End ``proc`` (SIGTERM, then SIGKILL) and return its exit status."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout_s)
    return proc.returncode


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
