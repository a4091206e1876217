"""Signals that end a mission the way Ctrl-C does: SIGTERM (a plain ``kill``, a service manager
stopping the daemon), SIGHUP (the terminal closed) and SIGINT (Ctrl-C).

The first one is raised in the main thread as ``MissionInterrupted`` (a ``KeyboardInterrupt``),
so the daemon's one exit path runs: RTL to every airborne vehicle, the result of what was flown.
While that cleanup runs, further signals are noted and ignored: a second Ctrl-C must not cut
the RTL short. The previous handlers come back on leaving the ``with`` block.
"""

from __future__ import annotations

import signal
from types import FrameType, TracebackType

from mavlink_bridge.mission.daemon import MissionInterrupted

#: exit status of a process ended by a signal, as a shell reports it (128 + its number)
EXIT_STATUS = {"SIGINT": 130, "SIGTERM": 143, "SIGHUP": 129}


class MissionSignals:
    """Context manager: SIGTERM/SIGHUP/SIGINT raise ``MissionInterrupted`` once."""

    def __init__(self) -> None:
        self.received: str | None = None
        self._previous: dict[int, object] = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.received is not None:
            return  # the cleanup of the first one is running
        self.received = signal.Signals(signum).name
        raise MissionInterrupted(self.received)

    def __enter__(self) -> MissionSignals:
        for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]

    @property
    def exit_status(self) -> int:
        return EXIT_STATUS.get(self.received or "", 130)
