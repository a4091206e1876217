"""A lane of its own for the tests that wait on the wall clock (pytest-xdist scheduling).

The suite runs on three pytest-xdist workers over the CI's two cores. Most tests need the CPU
(lockstep missions, offline runs, the SITL missions at 5x and 10x); a few spend minutes waiting
on the wall clock with the CPU nearly idle: the autopilots flown at real time (ArduPlane and PX4
SITL at 1x) and the demo that waits out its simulator's silence. Those are marked
``xdist_group("realtime")`` and run one after another on the last worker, which takes nothing
else; the other workers take everything else as ``--dist loadgroup`` does (each group on one
worker, the largest first: the SITL missions, tests/sitl/conftest.py). So three CPU-bound
workers never share two cores (three such workers starved the real-time autopilots: ArduPlane
SITL missed its pre-arm checks), and the waiting no longer adds to the busy workers' time.

With fewer than three workers there is no lane and the scheduling is pytest-xdist's own.
This leans on ``LoadScopeScheduling``'s work queue (pytest-xdist 3.5-3.8, pinned in
pyproject.toml).
"""

from __future__ import annotations

from xdist.scheduler import LoadGroupScheduling

#: the xdist group of the wall-clock-bound tests
REALTIME = "realtime"


class RealTimeLane(LoadGroupScheduling):
    """``--dist loadgroup`` with the group ``realtime`` on a worker of its own (the last)."""

    def _lane(self):
        """The lane's worker: the last of three or more, else None (no lane)."""
        if len(self.nodes) < 3:
            return None
        return max(self.nodes, key=lambda node: node.gateway.id)

    def _eligible(self, node) -> list[str]:
        """The queued work units ``node`` may take, in queue order."""
        lane = self._lane()
        if lane is None:
            return list(self.workqueue)
        return [scope for scope in self.workqueue if (scope == REALTIME) == (node is lane)]

    def _reschedule(self, node) -> None:
        """As pytest-xdist's, but a worker with nothing left that it may take is shut down
        (a worker runs its last test only once it knows there is no next one)."""
        if node.shutting_down:
            return
        if not self._eligible(node):
            node.shutdown()
            return
        if self._pending_of(self.assigned_work[node]) > 2:
            return
        self._assign_work_unit(node)

    def _assign_work_unit(self, node) -> None:
        """The first queued unit ``node`` may take, sent to it (nothing when there is none)."""
        eligible = self._eligible(node)
        if not eligible:
            return
        scope = eligible[0]
        work_unit = self.workqueue.pop(scope)
        self.assigned_work.setdefault(node, {})[scope] = work_unit
        collection = self.registered_collections[node]
        node.send_runtest_some(
            [collection.index(nodeid) for nodeid, done in work_unit.items() if not done]
        )
