"""The coordinator of ``swarmplan demo --onboard`` hears the swarm and serves the live view
(docs/onboard.md, "The coordinator hears the swarm"; docs/view.md): three UAVs of paper-10uav,
a short mission at 10x on loopback UDP with free ports, the view's WebSocket read over HTTP
(aiohttp, as the page does) while it flies. The view shows every node's vehicle at the position
its node measured from the simulator's telemetry at that step (``node-I/result.json``'s track),
coverage growing from the looks heard up to what the nodes' parts join to, and the progress
lines come from what the coordinator heard."""

from __future__ import annotations

import asyncio
import base64
import json
import re
import threading
import time
from pathlib import Path

import loopback
import pytest
from onboard_processes import end_processes, onboard_pids

from planner.scenario import load_scenario

STEPS = 12
UAVS = 3


def _scenario(tmp_path: Path) -> Path:
    text = (Path(loopback.REPO) / "planner/scenarios/paper-10uav.toml").read_text()
    path = tmp_path / f"paper-{UAVS}uav-view.toml"
    path.write_text(text.replace("count = 10", f"count = {UAVS}"))
    assert load_scenario(path).uav_count == UAVS
    return path


class ViewReader(threading.Thread):
    """Reads the live view's WebSocket to its end (``mission``, ``steps``, ``layer``,
    ``end``), in a thread of its own."""

    def __init__(self, url: str) -> None:
        super().__init__(daemon=True)
        self.url = url.split("?")[0].replace("http://", "ws://") + "ws"
        self.messages: list[dict] = []
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            asyncio.run(self._read())
        except BaseException as exc:  # (said by the test)
            self.error = exc

    async def _read(self) -> None:
        import aiohttp

        async with aiohttp.ClientSession() as session, session.ws_connect(self.url) as ws:
            await ws.send_str(json.dumps({"type": "view", "kind": "coverage", "step": None}))
            async for msg in ws:
                if msg.type != aiohttp.WSMsgType.TEXT:
                    break
                doc = json.loads(msg.data)
                self.messages.append(doc)
                if doc.get("type") == "end":
                    return

    def of(self, kind: str) -> list[dict]:
        return [m for m in self.messages if m.get("type") == kind]


def _view_url(log: Path, proc, timeout_s: float = 120.0) -> str:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        text = log.read_text(errors="replace") if log.exists() else ""
        found = re.search(r"live view at (http://127\.0\.0\.1:\d+/\S*)", text)
        if found:
            return found.group(1)
        assert proc.poll() is None, f"the demo exited without a live view: {text[-3000:]}"
        time.sleep(0.1)
    raise AssertionError(f"no live view URL within {timeout_s} s: {log.read_text()[-2000:]}")


@pytest.mark.timeout(300)
def test_the_coordinator_shows_what_it_hears_of_the_swarm(tmp_path):
    out, log = tmp_path / "run", tmp_path / "coordinator.log"
    args = ["demo", str(_scenario(tmp_path)), "--seed", "2", "--onboard", "--steps", str(STEPS),
            "--speedup", "10", "--out", str(out)]  # fmt: skip
    proc = loopback.start_swarmplan(args, log)
    pids: list[int] = []
    try:
        pids = onboard_pids(log, proc)
        reader = ViewReader(_view_url(log, proc))
        reader.start()
        proc.wait(260)
        reader.join(30)
    finally:
        loopback.stop(proc)
        end_processes(pids)  # (in sessions of their own: stopped by pid when the test fails)
    text = log.read_text(errors="replace")
    assert proc.returncode == 0, text[-3000:]
    assert reader.error is None and not reader.is_alive(), reader.error
    result = json.loads((out / "result.json").read_text())
    steps = [s for m in reader.of("steps") for s in m["steps"]]
    assert [s["step"] for s in steps] == list(range(STEPS + 1))  # every step, in order
    assert reader.of("end")

    # every node's vehicle, where its node measured it (the simulator's telemetry) at the step,
    # or (its report late or lost) at an earlier step of its track: never anywhere else
    tracks = [json.loads((out / f"node-{i}" / "result.json").read_text())["uavs"][0]["track_km"]
              for i in range(UAVS)]  # fmt: skip
    at_step = 0
    for s in steps:
        assert len(s["vehicles"]) == UAVS
        for i, v in enumerate(s["vehicles"]):
            near = [j for j, (x, y) in enumerate(tracks[i][: s["step"] + 1])
                    if abs(x - v["x_km"]) < 0.002 and abs(y - v["y_km"]) < 0.002]  # fmt: skip
            assert near, (s["step"], i, v, tracks[i])
            at_step += near[-1] == s["step"]
            assert v["last_heard_s"] is not None and v["signed"] is True
    assert at_step >= 0.8 * len(steps) * UAVS  # (a step shown before a busy node's report)
    assert any(v["x_km"] != tracks[0][0][0] for s in steps for v in s["vehicles"][:1])  # it moved

    # coverage from the looks heard: growing, up to the union of the nodes' own
    coverage = [s["coverage"] for s in steps]
    assert coverage == sorted(coverage) and coverage[-1] > coverage[1] > 0
    assert result["coverage"] * 0.9 <= coverage[-1] <= result["coverage"] + 1e-9
    layers = [m for m in reader.of("layer") if m["kind"] == "coverage"]
    assert layers and sum(base64.b64decode(layers[-1]["data"])) > 0

    heard = result["coordinator"]
    assert heard["reports"] > 0 and heard["steps_shown"] == STEPS + 1
    assert heard["wire"]["unsigned_or_forged"] == 0
    assert result["link"]["radio"]["ground"]["delivered"] == heard["frames"]
    # the progress lines say what was heard
    assert re.search(rf"coordinator: step {STEPS}/{STEPS} heard \({UAVS} of {UAVS} UAVs", text)
    assert (out / "replay.jsonl.gz").exists()
