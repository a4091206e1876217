"""The operator's side of the mission view in headless Chromium, over one lockstep demo
(paper-2uav) that is killed with SIGKILL half-way: the phase line through the launch and the
search, the vehicle panel, the disconnected banner with growing link ages after the server dies,
then ``swarmplan view`` of the cut-short replay: it opens at step 0, plays, says where it was
cut, and lays out at 390 px wide. ~40 s; skipped, saying why, where Chromium is missing."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
from browser import CHROMIUM_ARGS, chromium_or_skip, wait_for_url
from loopback import REPO, env, start_swarmplan, stop

STEPS = 60
KILL_AT = 12
pytestmark = pytest.mark.xdist_group("browser")


@pytest.fixture(scope="module")
def chromium():
    path = chromium_or_skip()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=path, args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


def open_page(chromium, url: str, width: int = 1280, height: int = 800):
    page = chromium.new_page(viewport={"width": width, "height": height})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.goto(url)
    page.wait_for_function("() => window.missionView && missionView.layout !== null")
    return page, errors


@pytest.fixture(scope="module")
def killed_demo(chromium, tmp_path_factory):
    """The demo flown with its page open, killed (it and its simulator: its process group) with
    SIGKILL at step KILL_AT: (page, console errors, phase lines seen by step, out folder)."""
    out = tmp_path_factory.mktemp("killed")
    log = out / "demo.log"
    args = ["demo", "paper-2uav", "--seed", "2", "--steps", str(STEPS), "--out", str(out)]
    with open(log, "ab") as sink:
        demo = subprocess.Popen(
            [sys.executable, "-m", "swarmplan", *args], stdout=sink, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, env=env(), cwd=REPO, start_new_session=True,
        )  # fmt: skip
    try:
        page, errors = open_page(chromium, wait_for_url(log, 60, demo))
        seen: dict[str, str] = {}  # step ("" before the first) -> phase line
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            step, phase = page.evaluate(
                "() => [document.body.dataset.step || '', document.getElementById('phase')"
                ".textContent]"
            )
            seen.setdefault(step, phase)
            if step and int(step) >= KILL_AT:
                break
            time.sleep(0.02)
        page.click(".uav-icon >> nth=1")  # the panel, before the server goes
        page.wait_for_selector("#vehicle-panel:not([hidden])")
        os.killpg(demo.pid, signal.SIGKILL)
        demo.wait(10)
        yield page, errors, seen, out
        page.close()
    finally:
        if demo.poll() is None:
            os.killpg(demo.pid, signal.SIGKILL)
            demo.wait(10)


@pytest.mark.timeout(200)
def test_phase_line_and_vehicle_panel_while_flying(killed_demo):
    """The phase line says launch before the first step and search from it on; clicking a UAV
    opens its panel with what its autopilot reports, and tells actions.js which UAV."""
    page, errors, seen, _ = killed_demo
    assert seen.get("", "").startswith("launch"), seen
    flying = {int(k): v for k, v in seen.items() if k}
    assert flying and all(v.startswith("search") for v in flying.values()), flying
    fields = page.evaluate(
        "() => Object.fromEntries(Array.from(document.querySelectorAll('#vp-fields dd'))"
        ".map(d => [d.dataset.field, d.textContent]))"
    )
    assert page.inner_text("#vp-name").startswith("UAV 2 at step")
    assert fields["flight mode"] == "GUIDED" and fields["planner mode"] != "n/a"
    assert fields["altitude"].endswith("m above home") and fields["battery"].endswith("%")
    assert fields["GPS"] == "3D fix" and "bearing" in fields["home"]
    assert fields["signing"] == "signed (MAVLink 2)" and "°S" in fields["guided target"]
    assert page.query_selector("#vehicle-panel #vehicle-actions") is not None
    selected = page.evaluate(
        "() => new Promise(done => { addEventListener('swarm:select', e => done(e.detail.uav),"
        " {once: true}); document.querySelector('#vehicles tbody tr[data-uav=\"0\"]').click(); })"
    )
    assert selected == 0
    assert not errors, errors


@pytest.mark.timeout(120)
def test_a_dead_server_is_obvious(killed_demo):
    """After SIGKILL: a banner, "follow live" off, link ages growing and marked stale, and
    reconnection attempts counted on the page."""
    page, errors, _, _ = killed_demo
    page.wait_for_selector("#banner.error:not([hidden])", timeout=10_000)
    assert "lost" in page.inner_text("#banner") and "Reconnecting" in page.inner_text("#banner")
    assert not page.evaluate("() => missionView.follow")
    assert "active" not in (page.get_attribute("#follow", "class") or "")
    read = "tds => tds.map(t => parseFloat(t.textContent))"
    ages = page.eval_on_selector_all("td.link.stale", read)
    time.sleep(2.5)
    later = page.eval_on_selector_all("td.link.stale", read)
    grown = all(b >= a + 1.5 for a, b in zip(ages, later, strict=True))
    assert len(later) == 2 and grown, (ages, later)
    assert page.evaluate("() => missionView.conn.attempts") >= 2
    assert "retrying" in page.inner_text("#connection")
    assert not [e for e in errors if "WebSocket" not in e], errors


@pytest.mark.timeout(120)
def test_replay_of_a_cut_mission_plays_and_fits_a_phone(chromium, killed_demo):
    """``swarmplan view`` of the killed demo: opens at step 0 with the phase of step 0, says
    where the recording stops, plays forward; at 390 px the map comes first and is not empty."""
    _, _, _, out = killed_demo
    log = out / "view.log"
    server = start_swarmplan(["view", str(out)], log)
    try:
        page, errors = open_page(chromium, wait_for_url(log, 30, server), 390, 844)
        page.wait_for_function("() => missionView.current === 0")
        assert page.inner_text("#phase").startswith("search")
        last = page.evaluate("() => missionView.steps[missionView.steps.length - 1].step")
        assert 0 < last < STEPS  # (the last steps may be in gzip's buffer when killed)
        assert page.inner_text("#endmark").startswith(f"cut short at step {last} of {STEPS}")
        page.select_option("#speed", "25")
        page.click("#play")
        page.wait_for_function("() => missionView.current >= 5", timeout=10_000)
        page.click("#play")  # pause
        paused = page.evaluate("() => missionView.current")
        time.sleep(0.3)
        assert page.evaluate("() => missionView.current") == paused
        boxes = page.evaluate(
            "() => ['map', 'vehicles'].map(id => { const r = document.getElementById(id)"
            ".getBoundingClientRect(); return [r.top, r.bottom, r.width, r.height]; })"
        )
        (map_top, map_bottom, map_w, map_h), (table_top, *_) = boxes
        assert map_h > 200 and map_w >= 380 and table_top >= map_bottom, boxes
        # by keyboard: no map shape is a Tab stop; timeline entries are buttons
        stops = "#map path:not([tabindex='-1'])[tabindex], #map .leaflet-marker-icon[tabindex='0']"
        assert page.eval_on_selector_all(stops, "els => els.length") == 0
        assert not errors, errors
        page.close()
    finally:
        assert stop(server) in (0, None)
