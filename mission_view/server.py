"""The view's web server: aiohttp on its own thread and event loop, serving the page (package
data in ``mission_view/static``, nothing from the internet) and one WebSocket per open page.

Per page, one sender task sends what changed since it last sent: new step views (never
skipped), the phase line, and the heat layer the page asked for (only the newest: a slow page
skips the layers in between instead of queueing them). The thread that feeds the store only
schedules a wake-up on the loop (``call_soon_threadsafe``), so it never waits for a page.

Messages to the page: ``mission`` (the layout, with ``tiles``: the map backdrop's URL template
or null), ``steps``, ``phase`` (``{"step": k, "text": ...}``: a phase line, from step k on; sent
in order, each once), ``layer`` (``data``: the
layer's bytes, base64, column-major cells (x, y) as ``belief_layers`` keeps them), ``end``. From
the page: ``{"type": "view", "kind": "coverage"|"tpm"|"pheromone", "uav": i, "step": k|null}``
(null: follow the newest step).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import threading
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web

from mission_view.belief_layers import LAYER_KINDS, layer_index
from mission_view.mission_store import MissionStore
from planner.errors import UserError

STATIC = Path(str(resources.files("mission_view") / "static"))


@dataclass(eq=False)  # one per open page, kept in a set by identity
class _Page:
    ws: web.WebSocketResponse
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    sent_steps: int = 0
    sent_phases: int = 0
    kind: str = "coverage"
    uav: int = 0
    step: int | None = None  # None: follow the newest
    layer_key: tuple[Any, ...] | None = None
    ended: bool = False


class ViewServer:
    """Serves ``store`` at ``http://HOST:PORT/`` (port 0: a free one) until ``stop``.
    ``tiles``: an XYZ tile URL template the page draws under the mission (None: no backdrop);
    ``port_option``: the option a port in use is to be changed with, in its error line."""

    def __init__(
        self,
        store: MissionStore,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        tiles: str | None = None,
        port_option: str = "--view-port, or --no-view",
    ) -> None:
        self.store = store
        self.host = host
        self.port = port
        self.tiles = tiles
        self.port_option = port_option
        self._pages: set[_Page] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._runner: web.AppRunner | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None
        store.subscribe(self._store_changed)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    # ------------------------------------------------------------------ life cycle

    def start(self) -> str:
        """Start the server's thread; returns its URL. A port that cannot be opened is a
        ``UserError``."""
        self._thread = threading.Thread(target=self._serve, name="mission-view-server", daemon=True)
        self._thread.start()
        self._started.wait(30)
        if self._error is not None:
            exc = self._error
            reason = getattr(exc, "strerror", None) or str(exc)
            raise UserError(
                f"cannot serve the view on {self.host}:{self.port} ({reason}); choose another "
                f"{self.port_option}"
            )
        return self.url

    def stop(self) -> None:
        loop = self._loop
        if loop is None or self._thread is None:
            return
        asyncio.run_coroutine_threadsafe(self._shutdown(), loop)
        self._thread.join(10)
        self._loop = None

    def _serve(self) -> None:
        loop = asyncio.new_event_loop()
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self._open())
        except Exception as exc:  # reported by start()
            self._error = exc
            self._started.set()
            loop.close()
            return
        self._loop = loop
        self._started.set()
        try:
            loop.run_forever()
        finally:
            loop.close()

    async def _open(self) -> None:
        app = web.Application()
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._websocket)
        app.router.add_static("/static/", STATIC, follow_symlinks=False)
        self._runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.host, self.port, reuse_address=True)
        await site.start()
        sockets = site._server.sockets if site._server is not None else []  # type: ignore[union-attr]
        if sockets:
            self.port = sockets[0].getsockname()[1]

    async def _shutdown(self) -> None:
        for page in list(self._pages):
            page.wake.set()
            await page.ws.close()
        if self._runner is not None:
            await self._runner.cleanup()
        asyncio.get_running_loop().stop()

    # ------------------------------------------------------------------ notifications

    def _store_changed(self) -> None:
        """Called in the feeding thread: wake every page's sender, without waiting."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
                loop.call_soon_threadsafe(self._wake_all)

    def _wake_all(self) -> None:
        for page in self._pages:
            page.wake.set()

    # ------------------------------------------------------------------ handlers

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse(heartbeat=20.0)
        await ws.prepare(request)
        page = _Page(ws)
        self._pages.add(page)
        sender = asyncio.create_task(self._send_loop(page))
        try:
            async for msg in ws:
                if msg.type != WSMsgType.TEXT:
                    continue
                self._read_request(page, msg.data)
                page.wake.set()
        finally:
            self._pages.discard(page)
            sender.cancel()
        return ws

    @staticmethod
    def _read_request(page: _Page, text: str) -> None:
        try:
            doc = json.loads(text)
        except ValueError:
            return
        if not isinstance(doc, dict) or doc.get("type") != "view":
            return
        if doc.get("kind") in LAYER_KINDS:
            page.kind = doc["kind"]
        if isinstance(doc.get("uav"), int) and doc["uav"] >= 0:
            page.uav = doc["uav"]
        step = doc.get("step")
        page.step = step if isinstance(step, int) and step >= 0 else None

    async def _send_loop(self, page: _Page) -> None:
        store, ws = self.store, page.ws
        try:
            await ws.send_str(json.dumps({**store.layout, "tiles": self.tiles}))
            page.wake.set()
            while not ws.closed:
                await page.wake.wait()
                page.wake.clear()
                for phase in store.phases_from(page.sent_phases):
                    page.sent_phases += 1
                    await ws.send_str(json.dumps({"type": "phase", **phase}))
                new = store.steps_from(page.sent_steps)
                if new:
                    page.sent_steps += len(new)
                    await ws.send_str(json.dumps({"type": "steps", "steps": new}))
                await self._send_layer(page)
                if store.ended and not page.ended:
                    page.ended = True
                    await ws.send_str(json.dumps({"type": "end"}))
        except (ConnectionError, asyncio.CancelledError):
            return

    async def _send_layer(self, page: _Page) -> None:
        n = int(self.store.layout["uav_count"])
        uav = min(page.uav, n - 1)
        found = self.store.layer(page.step, layer_index(page.kind, uav, n))
        if found is None:
            return
        step, layer = found
        key = (page.kind, uav, step)
        if key == page.layer_key:
            return
        page.layer_key = key
        doc = {
            "type": "layer",
            "kind": page.kind,
            "uav": uav,
            "step": step,
            "shape": list(layer.shape),
            "data": base64.b64encode(layer.tobytes()).decode("ascii"),
        }
        await page.ws.send_str(json.dumps(doc))
