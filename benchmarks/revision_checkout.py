"""What the ``--against REV`` benchmarks share: REV checked out into a temporary git worktree
(removed afterwards), and a digest of what a run flew, so that a change meant to keep the
decisions shows that it did ("same" tracks, engagements and decision modes)."""

from __future__ import annotations

import hashlib
import json
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


@contextmanager
def checked_out(rev: str, tool: str) -> Iterator[Path]:
    """REV (a commit or branch of this repository) in a temporary worktree; ``tool`` names the
    benchmark in the one-line error when git cannot check it out."""
    with tempfile.TemporaryDirectory(prefix=f"{tool}-") as tmp:
        tree = Path(tmp) / "before"
        added = subprocess.run(
            ["git", "-C", str(REPO), "worktree", "add", "--detach", "--quiet", str(tree), rev],
            capture_output=True, text=True, check=False,
        )  # fmt: skip
        if added.returncode != 0:
            reason = (added.stderr.strip().splitlines() or ["git failed"])[-1]
            raise SystemExit(f"{tool}: cannot check out {rev!r} ({reason}); give a commit or "
                             f"branch of this repository")  # fmt: skip
        try:
            yield tree
        finally:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)],
                           capture_output=True, check=False)  # fmt: skip


def flown_digest(results: list[dict]) -> str:
    """12 hex digits of the tracks, engagements and decision modes of ``results`` (offline runs'
    result dicts)."""
    flown = [
        [[u["track_km"] for u in r["uavs"]], r["engagements"], r["decision_modes"]] for r in results
    ]
    return hashlib.sha256(json.dumps(flown).encode()).hexdigest()[:12]
