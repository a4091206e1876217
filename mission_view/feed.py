"""The hand-over from a mission's decision loop to the view, which never makes the loop wait
(in live mode): the loop calls ``post`` once a step; it appends the step's ``StepView`` to a list
and, when a buffer is free, copies the planner's beliefs into it
(``planner.belief_snapshot``, ~0.4 ms for 10 UAVs); everything else (quantising the heat layers,
writing the replay, telling the server) happens in the feed's own thread. When that thread falls
behind, the beliefs of the steps in between are dropped (the replay then shows the nearest
earlier ones); step views never are.

Offline (``swarmplan run``) nothing waits for the run, so there ``post`` waits for a free buffer
and every step's beliefs are recorded.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Any

from mission_view.belief_layers import quantise
from mission_view.mission_store import MissionStore
from mission_view.replay_file import ReplayWriter
from mission_view.view_model import StepView
from planner.belief_snapshot import BeliefSnapshot, belief_snapshot
from planner.config import PlannerConfig

#: Snapshot buffers: one being filled by the loop while the feed's thread reads the other.
BUFFERS = 2


class ViewFeed:
    def __init__(
        self,
        store: MissionStore,
        config: PlannerConfig,
        writer: ReplayWriter | None = None,
        drop_beliefs: bool = True,
    ) -> None:
        self.store = store
        self.config = config
        self.writer = writer
        self.drop_beliefs = drop_beliefs
        self._cond = threading.Condition()
        self._views: deque[StepView] = deque()
        self._phases: deque[tuple[int, str]] = deque()  # (step, text)
        self._last_step = -1  # the newest step posted (-1: none yet)
        self._pending: BeliefSnapshot | None = None
        self._free: list[BeliefSnapshot | None] = [None] * BUFFERS
        self._closing = False
        self.dropped_beliefs = 0
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="mission-view-feed", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ the loop's side

    def post(self, view: StepView, planner: Any = None) -> None:
        """One decision step: its view, and the planner after it (read here, in the caller's
        thread, and never changed)."""
        slot: list[BeliefSnapshot | None] = []  # the buffer this step may copy into
        with self._cond:
            self._last_step = view.step
            self._views.append(view)  # turned into JSON in the feed's thread
            if planner is not None:
                if not self.drop_beliefs:  # recording every step: wait for the thread
                    self._cond.wait_for(
                        lambda: (self._free and self._pending is None) or self._closing
                    )
                if self._free:
                    slot.append(self._free.pop())
                elif self._pending is not None:  # the thread is behind: newer beliefs win
                    slot.append(self._pending)
                    self._pending = None
                    self.dropped_beliefs += 1
                else:  # both buffers in the thread's hands
                    self.dropped_beliefs += 1
            self._cond.notify_all()
        if not slot:
            return
        snapshot = belief_snapshot(planner, view.step, slot[0])  # outside the lock
        with self._cond:
            if snapshot is None:
                self._free.append(slot[0])
            else:
                if self._pending is not None:  # not taken yet: the newer one replaces it
                    self._free.append(self._pending)
                    self.dropped_beliefs += 1
                self._pending = snapshot
            self._cond.notify_all()

    def phase(self, text: str, step: int | None = None) -> None:
        """A line about the mission's phase (launch, search, return), from ``step`` on (None:
        the newest step posted; -1 before the first)."""
        with self._cond:
            self._phases.append((self._last_step if step is None else step, text))
            self._cond.notify_all()

    def close(self) -> None:
        """Process what is pending, close the replay file, mark the mission over."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self._thread.join()
        if self.writer is not None:
            self.writer.close()
        self.store.end()

    # ------------------------------------------------------------------ the feed's thread

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(
                    lambda: self._views or self._phases or self._pending or self._closing
                )
                views = list(self._views)
                self._views.clear()
                phases = list(self._phases)
                self._phases.clear()
                snapshot, self._pending = self._pending, None
                closing = self._closing and not views and not phases and snapshot is None
            if closing:
                return
            try:
                self._process(views, phases, snapshot)
            except Exception as exc:  # the view must never stop the mission
                self.error = exc
            finally:
                if snapshot is not None:
                    with self._cond:
                        self._free.append(snapshot)
                        self._cond.notify_all()

    def _process(
        self,
        step_views: list[StepView],
        phases: list[tuple[int, str]],
        snapshot: BeliefSnapshot | None,
    ) -> None:
        views = [view.to_json() for view in step_views]
        for step, text in phases:
            self.store.set_phase(text, step)
            if self.writer is not None:
                self.writer.write_phase(text, step)
        if views:
            self.store.add_steps(views)
            if self.writer is not None:
                self.writer.write_steps(views)
        if snapshot is not None:
            layers = quantise(snapshot, self.config)
            self.store.add_beliefs(snapshot.step, layers)
            if self.writer is not None:
                self.writer.write_beliefs(snapshot.step, layers)
