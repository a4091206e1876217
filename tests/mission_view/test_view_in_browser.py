"""The mission view in a real browser (headless Chromium through Playwright): the live page of a
running lockstep demo (30 steps of paper-2uav), then the replay of that demo with ``swarmplan
view``. Slow-ish (one short demo and two page loads, ~30 s); skipped, saying why, where no
Chromium is installed."""

from __future__ import annotations

import pytest
from browser import (
    heat_pixels,
    vehicle_positions,
    wait_for_url,
)
from loopback import start_swarmplan, stop

STEPS = 30
# the replay test views the live test's demo: both on one worker of pytest-xdist, in order (a
# group of this module's own: test_operator_view.py's demo can fly on the other worker meanwhile)
pytestmark = pytest.mark.xdist_group("view-in-browser")


@pytest.fixture(scope="module")
def demo_out(tmp_path_factory):
    return tmp_path_factory.mktemp("demo")


def open_page(chromium, url: str):
    page = chromium.new_page(viewport={"width": 1280, "height": 800})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(url)
    page.wait_for_function("() => window.missionView && missionView.layout !== null")
    return page, errors


@pytest.mark.timeout(180)
def test_live_view_of_a_running_demo(chromium, demo_out):
    """The page opens while the demo flies: it shows every vehicle, follows the steps as they
    pass, switches its heat layer on request, and ends with the mission."""
    log = demo_out / "demo.log"
    demo = start_swarmplan(
        ["demo", "paper-2uav", "--seed", "2", "--steps", str(STEPS), "--out", str(demo_out)], log
    )
    try:
        url = wait_for_url(log, 60, demo)
        page, errors = open_page(chromium, url)
        layout = page.evaluate("() => missionView.layout")
        assert layout["live"] and layout["uav_count"] == 2 and layout["steps"] == STEPS
        # the steps arrive one by one as the mission flies
        page.wait_for_function("() => missionView.renderedSteps.length >= 3", timeout=120_000)
        assert len(page.query_selector_all(".uav-icon")) == 2
        page.select_option("#layer-kind", "tpm")
        page.select_option("#layer-uav", "1")
        page.wait_for_function(
            "() => missionView.layerKind === 'tpm' && missionView.layerUav === 1", timeout=60_000
        )
        page.wait_for_function("() => missionView.ended", timeout=120_000)
        rendered = page.evaluate("() => missionView.renderedSteps")
        assert rendered == sorted(rendered) and len(set(rendered)) >= 3, rendered
        assert rendered[-1] == STEPS
        assert page.inner_text("#stepinfo") == f"step {STEPS} / {STEPS}"
        assert page.inner_text("#phase").startswith("return: RTL sent"), page.inner_text("#phase")
        # the simulator's true targets, drawn and marked as truth
        assert page.evaluate("() => missionView.layout.truth")
        assert len(page.query_selector_all("path.truth")) == 16  # the paper's targets
        rows = page.query_selector_all("#vehicles tbody tr")
        assert len(rows) == 2 and all("GUIDED" in r.inner_text() for r in rows)
        shot = demo_out / "live-view.png"
        page.screenshot(path=str(shot))
        assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert not errors, errors
        page.close()
        assert demo.wait(120) == 0
    finally:
        stop(demo)
    assert (demo_out / "replay.jsonl.gz").stat().st_size > 0


@pytest.mark.timeout(120)
def test_replay_slider_moves_the_vehicles_and_layers_change_the_picture(chromium, demo_out):
    """``swarmplan view`` of the demo above: the slider takes the vehicles back to the start and
    forward again, and the heat layer's pixels change with the layer shown."""
    if not (demo_out / "replay.jsonl.gz").exists():
        pytest.skip("the live-view test did not leave a replay")
    log = demo_out / "view.log"
    server = start_swarmplan(["view", str(demo_out)], log)
    try:
        page, errors = open_page(chromium, wait_for_url(log, 30, server))
        page.wait_for_function("() => missionView.current === 0")  # it opens at the start
        assert not page.evaluate("() => missionView.layout.live")
        assert page.inner_text("#phase").startswith("search"), page.inner_text("#phase")
        page.focus("#slider")
        page.keyboard.press("End")
        page.wait_for_function(f"() => missionView.current === {STEPS}")
        assert page.inner_text("#phase").startswith("return"), page.inner_text("#phase")
        at_end = vehicle_positions(page)
        page.keyboard.press("Home")
        page.wait_for_function("() => missionView.current === 0")
        at_start = vehicle_positions(page)
        assert len(at_start) == len(at_end) == 2
        assert all(a != b for a, b in zip(at_start, at_end, strict=True)), (at_start, at_end)
        page.keyboard.press("End")
        page.wait_for_function(f"() => missionView.current === {STEPS}")
        assert vehicle_positions(page) == at_end

        page.wait_for_function(f"() => missionView.layerStep === {STEPS}")
        coverage = heat_pixels(page)
        page.select_option("#layer-kind", "tpm")
        page.wait_for_function("() => missionView.layerKind === 'tpm'")
        tpm = heat_pixels(page)
        page.select_option("#layer-kind", "pheromone")
        page.wait_for_function("() => missionView.layerKind === 'pheromone'")
        pheromone = heat_pixels(page)
        assert coverage != tpm and tpm != pheromone and coverage != pheromone
        assert any(coverage[3::4]) and any(tpm[3::4])  # something is drawn (alpha)
        shot = demo_out / "replay.png"
        page.screenshot(path=str(shot))
        assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert not errors, errors
        page.close()
    finally:
        assert stop(server) in (0, None)
