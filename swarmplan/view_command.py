"""``swarmplan view RESULT_DIR``: replay a finished mission in the browser, with a time slider,
from the ``replay.jsonl.gz`` that ``swarmplan run``, ``demo`` and ``daemon`` write to their result
folder. Serves until Ctrl-C (or SIGTERM)."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path

from mission_view.replay_file import load_replay
from mission_view.server import ViewServer
from swarmplan.arguments import port_number
from swarmplan.option_groups import add_tiles_option

HELP = "replay a finished mission in the browser (time slider, beliefs as heat layers)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("result_dir", type=Path, help="the result folder of a run, demo or daemon")
    parser.add_argument(
        "--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)"
    )
    parser.add_argument(
        "--port", type=port_number, default=0, help="port (default 0: a free one, printed)"
    )
    add_tiles_option(parser)


def main(args: argparse.Namespace) -> int:
    store = load_replay(args.result_dir)
    server = ViewServer(
        store, args.host, args.port, tiles=args.tiles, port_option="--port (0: a free one)"
    )
    url = server.start()
    steps = store.step_count
    print(
        f"view: {store.layout['scenario']} seed {store.layout['seed']} ({steps} steps) at {url} "
        "(Ctrl-C to stop)",
        flush=True,
    )
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        while not stop.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)
        server.stop()
    print("view: stopped", file=sys.stderr)
    return 0
