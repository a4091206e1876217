"""The demo's end of the simulator's truth feed (``sim_gateway/truth_feed.py``): a UDP socket on
127.0.0.1 read without waiting; ``latest()`` is the newest true target list received, for the
step view of the decision step being shown (in lockstep the simulator holds at the decision
instant while the daemon decides, so the newest datagram is that instant's truth)."""

from __future__ import annotations

import json
import socket


class TruthReceiver:
    def __init__(self, host: str = "127.0.0.1") -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, 0))
        self.sock.setblocking(False)
        self.port = int(self.sock.getsockname()[1])
        self.targets: list[list[float]] | None = None

    def latest(self) -> list[list[float]] | None:
        """Drain what arrived; the newest well-formed target list (None before any)."""
        while True:
            try:
                data = self.sock.recv(65536)
            except (BlockingIOError, OSError):
                return self.targets
            try:
                targets = json.loads(data)["targets"]
                if isinstance(targets, list):
                    self.targets = targets
            except (ValueError, KeyError, TypeError):
                continue

    def close(self) -> None:
        self.sock.close()
