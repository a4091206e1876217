"""Headless Chromium for the mission view's tests: Debian's ``chromium`` (``/usr/bin/chromium``,
installed by ``.ci/run``) driven by Playwright through that binary; Playwright never downloads a
browser here. ``chromium_or_skip()`` says plainly why a test is skipped where either is missing."""

from __future__ import annotations

import os
import re
import shutil
import time
from pathlib import Path

import pytest

#: The flags this machine needs: no sandbox as root, and no background network at all.
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def chromium_path() -> str | None:
    explicit = os.environ.get("CHROMIUM")
    if explicit:
        return explicit if Path(explicit).exists() else None
    return shutil.which("chromium") or shutil.which("chromium-browser")


def chromium_or_skip() -> str:
    path = chromium_path()
    if path is None:
        pytest.skip("no Chromium installed (apt-get install -y chromium; .ci/run does it)")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        pytest.skip("Playwright is not installed (pip install '.[test]')")
    return path


def wait_for_url(log: Path, timeout_s: float, proc=None) -> str:
    """The first http:// URL written to ``log`` (the line the command prints at start)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        text = log.read_text(errors="replace") if log.exists() else ""
        found = re.search(r"http://127\.0\.0\.1:\d+/", text)
        if found:
            return found.group(0)
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"exited ({proc.returncode}) before printing its URL: {text}")
        time.sleep(0.05)
    raise AssertionError(f"no URL within {timeout_s} s in {log}")


def heat_pixels(page) -> list[int]:
    """The heat layer's canvas, as RGBA bytes."""
    return page.evaluate(
        "() => Array.from(missionView.heatCanvas.getContext('2d')"
        ".getImageData(0, 0, missionView.heatCanvas.width, missionView.heatCanvas.height).data)"
    )


def vehicle_positions(page, settle_s: float = 5.0) -> list[tuple[float, float]]:
    """Where each vehicle's marker is drawn on the page (centre of its element, pixels), once
    two reads 0.2 s apart agree (a marker still gliding to a new step, or the map still
    panning, is read where it comes to rest; at most ``settle_s``)."""
    now = _drawn_positions(page)
    deadline = time.monotonic() + settle_s
    while time.monotonic() < deadline:
        page.wait_for_timeout(200)
        now, before = _drawn_positions(page), now
        if now == before:
            break
    return now


def _drawn_positions(page) -> list[tuple[float, float]]:
    boxes = page.evaluate(
        "() => Array.from(document.querySelectorAll('.uav-icon')).map(e => {"
        " const r = e.getBoundingClientRect(); return [r.x + r.width / 2, r.y + r.height / 2]; })"
    )
    return [tuple(b) for b in boxes]
