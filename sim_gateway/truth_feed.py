"""The simulator's true targets for a display (``swarmplan sim --truth-port PORT``): one UDP
datagram per decision period to 127.0.0.1:PORT, JSON
``{"step": k, "time_s": t, "targets": [[id, x_km, y_km, alive], ...]}``. It goes to an operator's
display only (``swarmplan demo``'s live view marks it as truth); the planner never sees it, and it
is not MAVLink. Best effort: a datagram nobody reads is lost."""

from __future__ import annotations

import contextlib
import json
import socket

from sim_gateway.world import World


class TruthFeed:
    def __init__(self, port: int, host: str = "127.0.0.1") -> None:
        self.address = (host, port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def send(self, world: World, step: int) -> None:
        targets = [
            [int(i), round(float(x), 3), round(float(y), 3), int(alive)]
            for i, (x, y), alive in zip(world.target_ids, world.positions, world.alive, strict=True)
        ]
        doc = {"step": step, "time_s": round(world.time_s, 3), "targets": targets}
        # nobody listening, or the buffer full: the display misses one frame
        with contextlib.suppress(OSError):
            self.sock.sendto(json.dumps(doc, separators=(",", ":")).encode(), self.address)

    def close(self) -> None:
        self.sock.close()
