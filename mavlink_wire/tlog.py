"""Telemetry log (.tlog) of every MAVLink frame the daemon sends and receives.

The format is the one MAVProxy writes and pymavlink's ``mavutil.mavlink_connection(path)`` and
``mavlogdump.py`` read: for each frame an 8-byte big-endian timestamp in microseconds since the
Unix epoch, then the raw frame bytes.
"""

from __future__ import annotations

import struct
import threading
import time
from pathlib import Path
from typing import BinaryIO


class TlogWriter:
    """Appends timestamped raw frames to a .tlog file; safe to call from several threads."""

    def __init__(self, path: str | Path, append: bool = False) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # append: a restarted (resumed) daemon continues the log of the one that died
        mode = "ab" if append else "wb"
        self._file: BinaryIO | None = open(self.path, mode)  # noqa: SIM115 - closed in close()
        self._lock = threading.Lock()
        self.frames = 0

    def write(self, frame: bytes, timestamp_s: float | None = None) -> None:
        """Log one raw MAVLink frame (sent or received) with its time (now by default)."""
        if self._file is None:
            return
        usec = int((time.time() if timestamp_s is None else timestamp_s) * 1e6)
        with self._lock:
            self._file.write(struct.pack(">Q", usec) + bytes(frame))
            self.frames += 1

    def close(self) -> None:
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
