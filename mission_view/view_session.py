"""One mission's view, as a command sets it up: the store, the feed from the decision loop, the
replay file in the result folder and, for a live view, the server (see docs/view.md)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mission_view.belief_layers import LAYER_SCALES, layer_shape
from mission_view.feed import ViewFeed
from mission_view.mission_store import MissionStore
from mission_view.replay_file import ReplayWriter, replay_path
from mission_view.view_model import StepView, mission_layout
from planner.errors import UserError
from planner.scenario import Scenario


@dataclass(frozen=True)
class ViewOptions:
    """Whether and where a live view is served (``swarmplan daemon`` and ``demo`` take them
    from ``--no-view``, ``--view-host``, ``--view-port`` and ``--tiles``)."""

    serve: bool = True
    host: str = "127.0.0.1"
    port: int = 0  # 0: a free port, printed at start
    tiles: str | None = None  # an XYZ tile URL template for the map's backdrop (None: none)


class ViewSession:
    """Records a mission into ``out_dir/replay.jsonl.gz`` and, with ``options.serve``, serves
    it live. ``post`` once per decision step from the loop; ``close`` at the end."""

    def __init__(
        self,
        scenario: Scenario,
        *,
        seed: int,
        steps: int,
        uav_count: int,
        source: str,
        truth: bool,
        out_dir: Path | None,
        options: ViewOptions | None = None,
        live: bool = True,
        append: bool = False,
    ) -> None:
        """``append``: add to the replay already in ``out_dir`` (a resumed daemon)."""
        self.options = options or ViewOptions(serve=False)
        layout = mission_layout(
            scenario, seed=seed, steps=steps, uav_count=uav_count, source=source, live=live,
            truth=truth, layer_shape=layer_shape(scenario.config), layer_scales=LAYER_SCALES,
        )  # fmt: skip
        self.store = MissionStore(layout)
        self.writer = (
            None if out_dir is None else ReplayWriter(replay_path(out_dir), layout, append=append)
        )
        self.server = None
        self.url: str | None = None
        if self.options.serve:
            from mission_view.server import ViewServer

            self.server = ViewServer(
                self.store, self.options.host, self.options.port, tiles=self.options.tiles
            )
            try:
                self.url = self.server.start()
            except UserError:
                if self.writer is not None:
                    self.writer.close(ended=False)
                raise
        # a live mission never waits for the view; a recording-only run records every step
        self.feed = ViewFeed(self.store, scenario.config, self.writer, drop_beliefs=live)

    def post(self, view: StepView, planner: Any = None) -> None:
        self.feed.post(view, planner)

    def phase(self, text: str, step: int | None = None) -> None:
        self.feed.phase(text, step)

    def close(self) -> None:
        """The mission is over: record what is pending and close the replay file (the server,
        if any, keeps serving until ``stop``)."""
        self.feed.close()

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()
