"""Everything the page can ask for about one mission, shared between the thread that feeds it
and the server's thread: the layout, the step views so far, the quantised belief layers by step,
the phase lines (each from the step it was said at) and whether the mission is over. Readers
are told of changes by callbacks."""

from __future__ import annotations

import bisect
import threading
from collections.abc import Callable
from typing import Any

import numpy as np


class MissionStore:
    def __init__(self, layout: dict[str, Any]) -> None:
        self.layout = layout
        self._lock = threading.Lock()
        self._steps: list[dict[str, Any]] = []
        self._belief_steps: list[int] = []  # sorted
        self._beliefs: dict[int, np.ndarray] = {}  # step -> (layers, bx, by) uint8
        #: the phase lines so far, ``{"step": k, "text": ...}`` (k: the step it holds from, -1
        #: before the first), in the order said
        self.phases: list[dict[str, Any]] = []
        self.ended = False
        self._listeners: list[Callable[[], None]] = []

    # ------------------------------------------------------------------ writing

    def subscribe(self, listener: Callable[[], None]) -> None:
        """``listener()`` is called (in the writer's thread, so it must not block) on changes."""
        with self._lock:
            self._listeners.append(listener)

    def _changed(self) -> None:
        for listener in list(self._listeners):
            listener()

    def add_steps(self, steps: list[dict[str, Any]]) -> None:
        if not steps:
            return
        with self._lock:
            self._steps.extend(steps)
        self._changed()

    def add_beliefs(self, step: int, layers: np.ndarray) -> None:
        with self._lock:
            if step not in self._beliefs:
                bisect.insort(self._belief_steps, step)
            self._beliefs[step] = layers
        self._changed()

    def set_phase(self, text: str, step: int = -1) -> None:
        with self._lock:
            self.phases.append({"step": int(step), "text": text})
        self._changed()

    @property
    def phase(self) -> str:
        """The newest phase line ("" before any)."""
        return self.phases[-1]["text"] if self.phases else ""

    def phases_from(self, start: int) -> list[dict[str, Any]]:
        with self._lock:
            return self.phases[start:]

    def end(self) -> None:
        self.ended = True
        self._changed()

    # ------------------------------------------------------------------ reading

    @property
    def step_count(self) -> int:
        return len(self._steps)

    def steps_from(self, start: int) -> list[dict[str, Any]]:
        with self._lock:
            return self._steps[start:]

    def latest_belief_step(self) -> int | None:
        with self._lock:
            return self._belief_steps[-1] if self._belief_steps else None

    def layer(self, step: int | None, index: int) -> tuple[int, np.ndarray] | None:
        """Layer ``index`` of the beliefs recorded at ``step`` or, when that step has none
        (the view dropped it), at the nearest earlier step (the first one before any);
        ``step`` None: the newest. None when no beliefs are recorded."""
        with self._lock:
            if not self._belief_steps:
                return None
            if step is None:
                found = self._belief_steps[-1]
            else:
                at = bisect.bisect_right(self._belief_steps, step) - 1
                found = self._belief_steps[max(at, 0)]
            layers = self._beliefs[found]
        if not 0 <= index < len(layers):
            return None
        return found, layers[index]
