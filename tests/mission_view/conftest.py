"""The browser of the mission view's tests: one headless Chromium per test module."""

from __future__ import annotations

import pytest
from browser import CHROMIUM_ARGS, chromium_or_skip


@pytest.fixture(scope="module")
def chromium():
    """Debian's Chromium driven by Playwright (skipped, with the reason, where it is absent)."""
    path = chromium_or_skip()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=path, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()
