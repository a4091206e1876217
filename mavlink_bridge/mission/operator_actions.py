"""Operator actions: what an operator asks of a running mission from the mission view
(docs/view.md, "Operator actions"), queued by the view's server thread and carried out by the
decision loop's thread at the top of the next decision step, before the step is gathered and
planned.

- ``rtl`` (``uav``): the plane is out of the mission for good and flies the daemon's safe way
  home (``resume_takeback.send_planes_home``: RTL where its line home is clear, else guided
  around the threats, re-judged every step);
- ``rtl_all``: the same for every plane still in the mission; none is left, so the mission ends
  as a completed one does (the flight home watched, the result, the files);
- ``hold``: no new guided targets: every plane circles the target it last accepted (the loop's
  hold, ``keeping_up``: held planes kept d_min apart); the planner is still stepped with the
  measured positions and looks, so its beliefs, the range account and the mission clock go on;
- ``resume``: the search goes on from where the planes are;
- ``end``: the mission ends before this step, the normal way (``MissionDaemon.finish``: RTL,
  the watch of the flight home, result.json and the files);
- ``mark`` (``cell`` or ``lat``/``lon``): a reported sighting: every UAV's TPM takes a detection
  there (``planner.sighting``).

Every action applied is said (a progress line, the view's timeline) and kept for result.json
(``operator_actions``: step, time_utc of the request, action, uav, cell, who, result); refused
requests (a wrong or missing token, counted by the view's server) are counted
(``operator_refused``) and said once.
"""

from __future__ import annotations

import contextlib
import threading
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import numpy as np

from mavlink_bridge.mission.context import MissionContext
from mavlink_bridge.mission.resume_takeback import send_planes_home
from mavlink_bridge.vehicles.vehicle_loss import LossWatch
from mavlink_bridge.way_home.flight_home import FlightHomePhase
from mavlink_bridge.way_home.rtl_at_exit import rtl_recipients
from mavlink_wire.protocol import mavlink
from planner.belief_planner import beliefs_of
from planner.sighting import take_sighting

#: what each action does, in the words of the page and of ``check``
ACTIONS = {
    "rtl": "RTL one UAV",
    "rtl_all": "RTL all",
    "hold": "hold the search",
    "resume": "resume the search",
    "end": "end the mission",
    "mark": "mark a sighting",
}

#: why a plane the operator sent home is out of the mission (``LossWatch.retire``)
SENT_HOME = "sent home by the operator"


@dataclass(frozen=True)
class OperatorRequest:
    """One action asked for: by whom (the client's address) and when (UTC, ISO 8601)."""

    action: str
    who: str
    time_utc: str
    uav: int | None = None  # UAV index from 0 (system id - 1), for ``rtl``
    cell: tuple[int, int] | None = None  # grid cell (ix, iy), for ``mark``


class OperatorInbox:
    """The queue between the view's server (any thread: ``submit``, ``refuse``) and the decision
    loop (``take``). Each request gets a ``Future`` the loop resolves with what happened."""

    def __init__(self, ctx: MissionContext) -> None:
        self.ctx = ctx
        self._lock = threading.Lock()
        self._queue: list[tuple[OperatorRequest, Future]] = []
        self.closed: str | None = None  # why no more actions are taken
        self.refused = 0  # requests with a wrong or missing token
        self.refused_from: list[str] = []  # who, until said (once)
        self.refusal_said = False
        self.step: int | None = None  # the decision step the loop is at (None: not yet)

    def submit(self, doc: dict[str, Any], who: str) -> Future:
        """Queue the action ``doc`` asks for (its token already checked). A bad request is a
        ``ValueError`` with one line saying what is wrong; ``check`` answers at once."""
        action = doc.get("action")
        done: Future = Future()
        if action == "check":
            done.set_result(self.status())
            return done
        if action not in ACTIONS:
            raise ValueError(f"unknown action {action!r}: one of {', '.join(ACTIONS)}")
        now = datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
        request = OperatorRequest(
            action, who, now, self.uav_of(doc) if action == "rtl" else None,
            self.cell_of(doc) if action == "mark" else None,
        )  # fmt: skip
        with self._lock:
            if self.closed is not None:
                done.set_result({"applied": False, "result": f"not applied: {self.closed}"})
            else:
                self._queue.append((request, done))
        return done

    def status(self) -> dict[str, Any]:
        """What ``check`` answers: whether actions are taken now, and the mission's shape."""
        grid = self.ctx.grid
        return {
            "applied": True,
            "open": self.closed is None,
            "reason": self.closed,
            "step": self.step,
            "actions": ACTIONS,
            "uav_count": self.ctx.n,
            "grid": [grid.nx, grid.ny],
            "cell_km": grid.cell_km,
        }

    def uav_of(self, doc: dict[str, Any]) -> int:
        uav = doc.get("uav")
        if not isinstance(uav, int) or isinstance(uav, bool) or not 0 <= uav < self.ctx.n:
            raise ValueError(f"rtl needs uav: a UAV index 0..{self.ctx.n - 1}, got {uav!r}")
        return uav

    def cell_of(self, doc: dict[str, Any]) -> tuple[int, int]:
        """The grid cell of a sighting: ``cell`` [ix, iy], or ``lat`` and ``lon`` (degrees)."""
        grid = self.ctx.grid
        if doc.get("cell") is not None:
            cell = doc["cell"]
            ok = isinstance(cell, list | tuple) and len(cell) == 2
            if not ok or not all(isinstance(c, int) and not isinstance(c, bool) for c in cell):
                raise ValueError(f"cell must be [ix, iy], two whole numbers, got {cell!r}")
        else:
            lat, lon = doc.get("lat"), doc.get("lon")
            if not all(isinstance(v, int | float) and np.isfinite(v) for v in (lat, lon)):
                raise ValueError("mark needs cell [ix, iy] or lat and lon in degrees")
            xy = self.ctx.local_km(float(lat), float(lon))
            cell = [int(np.floor(c / grid.cell_km)) for c in xy]
        if not (0 <= cell[0] < grid.nx and 0 <= cell[1] < grid.ny):
            raise ValueError(
                f"the sighting's cell ({cell[0]}, {cell[1]}) is outside the mission area "
                f"(cells 0..{grid.nx - 1}, 0..{grid.ny - 1})"
            )
        return int(cell[0]), int(cell[1])

    def refuse(self, who: str) -> None:
        """A request with a wrong or missing token (the server answered 403): counted, said
        once by the loop."""
        with self._lock:
            self.refused += 1
            if not self.refusal_said:
                self.refused_from.append(who)

    def take(self) -> list[tuple[OperatorRequest, Future]]:
        with self._lock:
            taken, self._queue = self._queue, []
        return taken

    def close(self, why: str) -> None:
        """No more actions (the mission is over): the ones still queued are answered so."""
        with self._lock:
            self.closed = why
            left, self._queue = self._queue, []
        for _, done in left:
            answer(done, {"applied": False, "result": f"not applied: {why}"})


@dataclass
class OperatorActions:
    """Carries out the inbox's requests in the decision loop (see the module docstring)."""

    ctx: MissionContext
    home: FlightHomePhase
    loss: LossWatch
    inbox: OperatorInbox = field(init=False)
    holding: bool = False  # the search is held: no new guided targets
    held_steps: int = 0
    ended: str | None = None  # the loop ends before its next step, with this ``ended``
    log: list[dict[str, Any]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.inbox = OperatorInbox(self.ctx)

    def apply(self, step: int, planner: Any) -> bool:
        """The requests queued since the last step, in order, at decision step ``step``; True
        when there were any."""
        self.say_refusals()
        self.inbox.step = step
        taken = self.inbox.take()
        for request, done in taken:
            try:
                result = self.carry_out(request, step, planner)
            except Exception as exc:  # noqa: BLE001 - one action's failure is said, not fatal
                result = f"failed: {type(exc).__name__}: {exc}"
            self.log.append(
                {
                    "step": step, "time_utc": request.time_utc, "action": request.action,
                    "uav": request.uav, "cell": request.cell and list(request.cell),
                    "who": request.who, "result": result,
                }  # fmt: skip
            )
            self.ctx.say(f"operator ({request.who}): {ACTIONS[request.action]}: {result}")
            answer(done, {"applied": True, "step": step, "result": result})
        if self.ended is None and self.ctx.n and len(self.loss.retired) >= self.ctx.n:
            self.ended = f"completed early: every plane sent home by the operator (step {step})"
        return bool(taken)

    def carry_out(self, request: OperatorRequest, step: int, planner: Any) -> str:
        action = request.action
        if action in ("rtl", "rtl_all"):
            uavs = [request.uav] if action == "rtl" else list(range(self.ctx.n))
            return self.send_home([u for u in uavs if u is not None])
        if action == "hold":
            was, self.holding = self.holding, True
            return "already held" if was else "held: every plane circles its last target"
        if action == "resume":
            was, self.holding = self.holding, False
            return "resumed: the search goes on" if was else "not held: nothing to resume"
        if action == "end":
            self.ended = f"completed early: ended by the operator before step {step}"
            return "the mission ends now: RTL, the flight home, the result"
        assert request.cell is not None
        return self.mark(request.cell, planner)

    def send_home(self, uavs: list[int]) -> str:
        """The planes ``uavs`` out of the mission and home (``send_planes_home``); says who
        could not be (already sent home, not flying or unreachable)."""
        retired = {u for u in uavs if u in self.loss.retired}
        fresh = [self.ctx.vehicle(u) for u in uavs if u not in retired]
        flying, skipped = rtl_recipients(fresh, self.ctx.options.lost_after_s)
        sent = send_planes_home(
            self.ctx, self.home, self.loss,
            {v.key: SENT_HOME for v in flying}, SENT_HOME,
        )  # fmt: skip
        parts = []
        rtl = [c for c in sent if c.command == mavlink.MAV_CMD_DO_SET_MODE]
        if rtl:
            accepted = [str(c.vehicle.key) for c in rtl if c.accepted]
            parts.append(f"RTL accepted by vehicle {', '.join(accepted) or 'none'}")
        around = [str(c.vehicle.key) for c in sent if c not in rtl]
        if around:
            parts.append(f"guided home around the threats: vehicle {', '.join(around)}")
        if retired:
            parts.append(f"already sent home: {', '.join(str(u + 1) for u in sorted(retired))}")
        parts += [f"not vehicle {sid} ({why})" for sid, why in skipped.items()]
        return "; ".join(parts) or "no plane to send home"

    def mark(self, cell: tuple[int, int], planner: Any) -> str:
        """A reported sighting at ``cell`` into every UAV's beliefs (``planner.sighting``)."""
        beliefs = beliefs_of(planner)
        if beliefs is None:
            return "not taken: this planner keeps no beliefs"
        n = beliefs.n
        at = np.repeat(np.array(cell)[None, None, :], n, axis=0)
        before = beliefs.tpm.existence_at(np.arange(n)[:, None], at)
        take_sighting(beliefs, cell)
        after = beliefs.tpm.existence_at(np.arange(n)[:, None], at)
        return (
            f"sighting at cell ({cell[0]}, {cell[1]}) taken in by every UAV: existence "
            f"{float(before.mean()):.3f} -> {float(after.mean()):.3f}"
        )

    def watched_home(self) -> None:
        """At the mission's exit: the planes the operator sent home that are still reachable are
        no longer lost, so that the watch of the flight home (``home_watch.watch_flight_home``)
        waits for them too, as for every other plane (they were lost to the planner only)."""
        retired = {u for u, why in self.loss.retired.items() if why == SENT_HOME}
        flying, _ = rtl_recipients(
            [self.ctx.vehicle(u) for u in sorted(retired)], self.ctx.options.lost_after_s
        )
        for v in flying:
            v.lost = False

    def say_refusals(self) -> None:
        """Said once: requests with a wrong or missing token were refused (all are counted)."""
        inbox = self.inbox
        if inbox.refusal_said or not inbox.refused_from:
            return
        inbox.refusal_said = True
        self.ctx.say(
            f"warning: the view refused an operator action with a wrong or missing token (from "
            f"{inbox.refused_from[0]}); every such request is counted in result.json "
            "(operator_refused)"
        )

    def result(self) -> dict[str, Any]:
        """The operator's part of result.json."""
        return {
            "operator_actions": list(self.log),
            "operator_refused": self.inbox.refused,
            "operator_held_steps": self.held_steps,
        }


def answer(done: Future, result: dict[str, Any]) -> None:
    """Resolve a request's future, unless its asker gave up on it (cancelled): the loop never
    fails for an answer nobody waits for."""
    if not done.done():
        with contextlib.suppress(InvalidStateError):
            done.set_result(result)
