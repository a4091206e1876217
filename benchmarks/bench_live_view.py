"""The live view's cost to a mission: the demo's lockstep 10-UAV mission (``swarmplan demo``,
simulator + daemon over loopback UDP) flown with the view off (``--no-view``) and on, with a
client connected that reads everything the server sends and asks for a UAV's target probability
map (what an open page does), alternating off / on so both see the same machine load.

    python benchmarks/bench_live_view.py [--repeats 3] [--steps 250] [--seed 1]

Prints each run's wall time of the mission (launch + decision loop, the result's
``wall_time_s``), the median wall time of one decision step (from the replay's per-step clock;
the replay is written with the view off too), the messages and bytes the client got, then the
medians over the runs and the ratios on / off (1.00: no slower). The view's threads run beside
the decision loop; its snapshot of the beliefs (~0.4 ms a step for 10 UAVs) is the only work it
adds to the loop itself.
"""

from __future__ import annotations

import argparse
import asyncio
import gzip
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import aiohttp

REPO = Path(__file__).resolve().parents[1]


class PageClient(threading.Thread):
    """A WebSocket client like the page: asks for UAV 1's TPM and reads until the server
    closes."""

    def __init__(self, url: str) -> None:
        super().__init__(daemon=True)
        self.url = url.replace("http://", "ws://") + "ws"
        self.messages = 0
        self.bytes = 0
        self.steps = 0

    def run(self) -> None:
        asyncio.run(self._read())

    async def _read(self) -> None:
        async with aiohttp.ClientSession() as session, session.ws_connect(self.url) as ws:
            await ws.send_str(json.dumps({"type": "view", "kind": "tpm", "uav": 1, "step": None}))
            async for msg in ws:
                if msg.type != aiohttp.WSMsgType.TEXT:
                    break
                self.messages += 1
                self.bytes += len(msg.data)
                if '"type":"steps"' in msg.data.replace(" ", ""):
                    self.steps += len(json.loads(msg.data)["steps"])


def step_ms(out: Path) -> float:
    """Median wall time of a decision step (ms): the mission's replay records each step's wall
    clock (written with the view off too), and the median shrugs off the other work of a
    shared machine better than the total does."""
    with gzip.open(out / "replay.jsonl.gz", "rt") as lines:
        walls = [json.loads(line)["wall_s"] for line in lines if line.startswith('{"type":"step"')]
    gaps = [b - a for a, b in zip(walls, walls[1:], strict=False)]
    return 1e3 * statistics.median(gaps)


def fly(seed: int, steps: int, view: bool, out: Path) -> tuple[float, PageClient | None]:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    args = ["demo", "paper-10uav", "--seed", str(seed), "--steps", str(steps), "--json"]
    args += ["--out", str(out)] + ([] if view else ["--no-view"])
    proc = subprocess.Popen(
        [sys.executable, "-m", "swarmplan", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO,
    )  # fmt: skip
    client = None
    if view:
        assert proc.stderr is not None
        for line in proc.stderr:
            found = re.search(r"http://127\.0\.0\.1:\d+/", line)
            if found:
                client = PageClient(found.group(0))
                client.start()
                break
    stdout, stderr = proc.communicate(timeout=900)
    if proc.returncode != 0:
        raise SystemExit(f"swarmplan {' '.join(args)} failed: {stderr.strip()[-500:]}")
    if client is not None:
        client.join(10)
    return float(json.loads(stdout)["wall_time_s"]), client


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--steps", type=int, default=250)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    times: dict[bool, list[float]] = {False: [], True: []}
    step_times: dict[bool, list[float]] = {False: [], True: []}
    print(f"paper-10uav seed {args.seed}, {args.steps} steps, lockstep demo; {args.repeats} "
          "runs each, alternating", flush=True)  # fmt: skip
    print(
        f"{'run':>4} {'view':>5} {'wall s':>8} {'step ms':>8} {'messages':>9} {'kB sent':>8} "
        f"{'steps seen':>10}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for view in (False, True):
                out = Path(tmp) / f"{r}-{view}"
                wall, client = fly(args.seed, args.steps, view, out)
                times[view].append(wall)
                step_times[view].append(step_ms(out))
                extra = (
                    f"{client.messages:>9} {client.bytes / 1e3:>8.0f} {client.steps:>10}"
                    if client is not None
                    else f"{'-':>9} {'-':>8} {'-':>10}"
                )
                print(
                    f"{r + 1:>4} {'on' if view else 'off':>5} {wall:>8.2f} "
                    f"{step_times[view][-1]:>8.1f} {extra}",
                    flush=True,
                )
    off, on = statistics.median(times[False]), statistics.median(times[True])
    print(f"median mission wall time: view off {off:.2f} s, on {on:.2f} s, ratio {on / off:.3f}")
    off, on = statistics.median(step_times[False]), statistics.median(step_times[True])
    print(f"median decision step: view off {off:.1f} ms, on {on:.1f} ms, ratio {on / off:.3f}")


if __name__ == "__main__":
    main()
