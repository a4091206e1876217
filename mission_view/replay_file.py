"""The replay file of a mission, ``replay.jsonl.gz`` in its result folder: what ``swarmplan
view`` needs to show it again. One JSON object a line, gzip-compressed:

* ``{"type": "mission", ...}``: the layout (``view_model.mission_layout``), first;
* ``{"type": "step", ...}``: a ``StepView`` per decision step;
* ``{"type": "beliefs", "step": k, "data": ...}``: the quantised belief layers of step k
  (``belief_layers``), as the byte-wise difference (mod 256) from the previous beliefs line,
  zlib-compressed, base64 (consecutive steps differ in few cells: ~2 MB for the paper's 10-UAV
  mission of 250 steps); ``"key": true`` marks whole layers (a writer's first line);
* ``{"type": "phase", "step": k, "text": ...}`` (the phase line from step k on; -1: before the
  first) and ``{"type": "end"}`` (absent when the mission was cut short: the page says so).

Lines are written as they come, so a mission cut short leaves a file that reads up to its last
complete line. A daemon resumed from its checkpoint appends a gzip member of its own (layout,
steps, beliefs from a key line); a step found twice is read from the later one.
"""

from __future__ import annotations

import base64
import gzip
import json
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from mission_view.mission_store import MissionStore
from planner.errors import UserError

REPLAY_NAME = "replay.jsonl.gz"


class ReplayWriter:
    def __init__(self, path: Path, layout: dict[str, Any], append: bool = False) -> None:
        self.path = Path(path)
        try:
            self._file = gzip.open(  # noqa: SIM115 - open for the mission, closed by close()
                self.path, "at" if append else "wt", compresslevel=1, encoding="utf-8"
            )
        except OSError as exc:
            raise UserError(
                f"cannot write the replay {self.path} ({exc.strerror}); choose another --out"
            ) from None
        self._previous: np.ndarray | None = None
        self._write(layout)

    def _write(self, doc: dict[str, Any]) -> None:
        self._file.write(json.dumps(doc, separators=(",", ":")) + "\n")

    def write_steps(self, steps: list[dict[str, Any]]) -> None:
        for step in steps:
            self._write({"type": "step", **step})

    def write_beliefs(self, step: int, layers: np.ndarray) -> None:
        key = self._previous is None  # the first of this writer: whole layers, not a difference
        delta = layers if key else layers - self._previous
        self._previous = layers
        data = base64.b64encode(zlib.compress(delta.tobytes(), 1)).decode("ascii")
        doc = {"type": "beliefs", "step": step, "shape": list(layers.shape), "data": data}
        self._write({**doc, "key": True} if key else doc)

    def write_phase(self, text: str, step: int = -1) -> None:
        self._write({"type": "phase", "step": step, "text": text})

    def close(self, ended: bool = True) -> None:
        if self._file.closed:
            return
        if ended:
            self._write({"type": "end"})
        self._file.close()


def replay_path(result_dir: Path) -> Path:
    return Path(result_dir) / REPLAY_NAME


def load_replay(result_dir: Path) -> MissionStore:
    """The store of a recorded mission, for ``swarmplan view``. A bad folder or file is a
    ``UserError`` naming it."""
    path = replay_path(result_dir)
    if not Path(result_dir).is_dir():
        raise UserError(f"{result_dir} is not a folder; give the result folder of a run")
    if not path.is_file():
        raise UserError(
            f"{result_dir} has no {REPLAY_NAME}; fly the mission again with swarmplan run, demo "
            "or daemon (they write it to their --out folder)"
        )
    store: MissionStore | None = None
    previous: np.ndarray | None = None
    steps: dict[int, dict[str, Any]] = {}
    last_step, ended = -1, False
    try:
        with gzip.open(path, "rt", encoding="utf-8") as lines:
            for number, line in enumerate(_complete_lines(lines), start=1):
                doc = json.loads(line)
                kind = doc.pop("type", None)
                if store is None:
                    if kind != "mission":
                        raise ValueError("it does not start with the mission layout")
                    store = MissionStore({"type": "mission", **doc, "live": False})
                elif kind == "mission":  # a resumed daemon appended its part: same mission
                    continue
                elif kind == "step":
                    last_step, ended = int(doc["step"]), False
                    steps[last_step] = doc  # a step flown again after a resume: the later
                elif kind == "beliefs":
                    raw = zlib.decompress(base64.b64decode(doc["data"]))
                    delta = np.frombuffer(raw, dtype=np.uint8).reshape(doc["shape"])
                    key = previous is None or doc.get("key", False)
                    layers = delta.copy() if key else previous + delta
                    previous = layers
                    store.add_beliefs(int(doc["step"]), layers)
                elif kind == "phase":  # (files before phase steps: the step read last)
                    store.set_phase(str(doc.get("text", "")), int(doc.get("step", last_step)))
                elif kind == "end":
                    ended = True
                else:
                    raise ValueError(f"line {number} has an unknown type {kind!r}")
    except (OSError, EOFError, ValueError, KeyError, TypeError, zlib.error) as exc:
        raise UserError(f"cannot read {path} ({exc}); the file is damaged") from None
    if store is None:
        raise UserError(f"{path} is empty; fly the mission again")
    store.add_steps([steps[k] for k in sorted(steps)])
    # no end line after the last step: the recording stops there (kill -9, power cut)
    store.layout["cut_short"] = not ended
    store.ended = True
    return store


def _complete_lines(lines: Any) -> Any:
    """The lines of a gzip text stream up to the last complete one (a mission cut short leaves
    a truncated stream)."""
    try:
        for line in lines:
            if line.endswith("\n"):
                yield line
    except EOFError:
        return
