"""Operator actions from the mission view (docs/view.md, "Operator actions") on real lockstep
missions of paper-2uav over loopback UDP. ``swarmplan sim`` with ``swarmplan daemon`` (the URL with
the token the daemon prints): refused without the view's token (403, counted in result.json), RTL
all over HTTP (both vehicles' heartbeats in RTL, the mission ended early, the normal way). And
``swarmplan demo`` clicked through the page in headless Chromium: mark a sighting, hold and resume
(no guided target sent while held), RTL one UAV (its heartbeats in RTL, the other's not; "sent
home (operator)" on the page, not "LOST") and end the mission (result.json written early, with
every action, who and when). One mission of ~15-25 s per test (each test stands alone: under
pytest-xdist the tests of one module may run on different workers)."""

from __future__ import annotations

import json
import re
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from loopback import free_udp_port, start_swarmplan, stop

from mavlink_wire.protocol import PLANE_MODE_RTL

STEPS = 250  # the scenario's; every mission here is ended early by its operator


class Demo:
    """A running mission with its view: ``swarmplan demo`` or, with ``daemon``, ``swarmplan
    sim`` and ``swarmplan daemon`` (lockstep); the daemon's process, the view's URL with its
    token, its folder."""

    def __init__(self, out: Path, daemon: bool = False) -> None:
        self.out = out
        self.log = out / ("daemon.log" if daemon else "demo.log")
        self.sim = None
        if daemon:
            port = free_udp_port()
            self.sim = start_swarmplan(
                ["sim", "--scenario", "paper-2uav", "--seed", "2", "--lockstep", "--speedup",
                 "100", "--gcs-port", str(port), "--quiet"], out / "sim.log",
            )  # fmt: skip
            args = ["daemon", "--connect", f"udpin:127.0.0.1:{port}", "--scenario", "paper-2uav",
                    "--seed", "2", "--lockstep", "--timeout", "30", "--out", str(out)]  # fmt: skip
        else:
            args = ["demo", "paper-2uav", "--seed", "2", "--out", str(out)]
        self.proc = start_swarmplan(args, self.log)
        self.url = self.token_url(60)
        self.base, self.token = self.url.split("?token=")

    def stop(self) -> None:
        stop(self.proc)
        if self.sim is not None:
            stop(self.sim)

    def token_url(self, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            text = self.log.read_text(errors="replace") if self.log.exists() else ""
            found = re.search(r"http://127\.0\.0\.1:\d+/\?token=[\w-]+", text)
            if found:
                return found.group(0)
            assert self.proc.poll() is None, f"the demo exited: {text}"
            time.sleep(0.05)
        raise AssertionError(f"no view URL with a token within {timeout_s} s")

    def wait_step(self, step: int, timeout_s: float = 90) -> None:
        """Until the mission's decision loop is at ``step`` (``check`` says where it is)."""
        deadline = time.monotonic() + timeout_s
        while (self.post({"token": self.token, "action": "check"})[1]["step"] or 0) < step:
            assert time.monotonic() < deadline and self.proc.poll() is None
            time.sleep(0.1)

    def post(self, doc: dict) -> tuple[int, dict]:
        request = urllib.request.Request(
            self.base + "api/action", json.dumps(doc).encode(), {"Content-Type": "application/json"}
        )
        try:
            with urllib.request.urlopen(request, timeout=30) as answer:
                return answer.status, json.loads(answer.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())

    def result(self) -> dict:
        assert self.proc.wait(120) == 0, self.log.read_text(errors="replace")[-3000:]
        return json.loads((self.out / "result.json").read_text())


@pytest.fixture
def http_daemon(tmp_path_factory):
    demo = Demo(tmp_path_factory.mktemp("operator-http"), daemon=True)
    try:
        yield demo
    finally:
        demo.stop()


@pytest.fixture
def page_demo(tmp_path_factory, chromium):
    demo = Demo(tmp_path_factory.mktemp("operator-page"))
    try:
        yield demo, chromium
    finally:
        demo.stop()


def heartbeats(tlog: Path) -> list[tuple[float, int, int]]:
    """(time, system id, custom mode) of every vehicle HEARTBEAT in the daemon's .tlog."""
    from pymavlink import mavutil

    log = mavutil.mavlink_connection(str(tlog), robust_parsing=True)
    found = []
    while (msg := log.recv_match(type="HEARTBEAT")) is not None:
        if msg.get_srcComponent() == 1 and msg.get_srcSystem() < 250:
            found.append((msg._timestamp, msg.get_srcSystem(), msg.custom_mode))
    return found


def repositions(tlog: Path) -> list[float]:
    """Times of every DO_REPOSITION the daemon sent (its guided targets)."""
    from pymavlink import mavutil

    log = mavutil.mavlink_connection(str(tlog), robust_parsing=True)
    times = []
    while (msg := log.recv_match(type=["COMMAND_INT", "COMMAND_LONG"])) is not None:
        if msg.command == mavutil.mavlink.MAV_CMD_DO_REPOSITION:
            times.append(msg._timestamp)
    return times


def utc_s(stamp: str) -> float:
    from datetime import datetime

    return datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()


@pytest.mark.timeout(180)
def test_refused_without_the_token_then_rtl_all_sends_every_vehicle_home(http_daemon):
    """``swarmplan daemon``'s view (the URL with the token it prints). No token and a wrong
    one: 403, nothing done, counted; bad requests are one line; then RTL all: both vehicles'
    heartbeats in RTL after it (not before), the mission ended early the normal way."""
    assert http_daemon.post({"action": "end"})[0] == 403
    assert http_daemon.post({"token": http_daemon.token[:-1] + "x", "action": "rtl_all"})[0] == 403
    status, answer = http_daemon.post({"token": http_daemon.token, "action": "check"})
    assert status == 200 and answer["open"] and answer["uav_count"] == 2
    status, answer = http_daemon.post({"token": http_daemon.token, "action": "rtl", "uav": 7})
    assert status == 400 and "0..1" in answer["error"]
    nowhere = {"token": http_daemon.token, "action": "mark", "lat": 0.0, "lon": 0.0}
    status, answer = http_daemon.post(nowhere)
    assert status == 400 and "outside the mission area" in answer["error"]

    http_daemon.wait_step(5)  # a few steps out: their flight home lasts a few heartbeats
    status, answer = http_daemon.post({"token": http_daemon.token, "action": "rtl_all"})
    assert status == 200, answer
    assert "RTL accepted by vehicle 1, 2" in answer["result"]
    result = http_daemon.result()
    assert result["ended"].startswith("completed early: every plane sent home by the operator")
    assert result["steps"] < STEPS
    assert [a["action"] for a in result["operator_actions"]] == ["rtl_all"]
    assert result["operator_refused"] == 2  # the two above
    asked = utc_s(result["operator_actions"][0]["time_utc"])
    modes = heartbeats(http_daemon.out / "mission.tlog")
    for sid in (1, 2):  # each vehicle said RTL in its heartbeats, after the operator asked
        assert any(t >= asked - 1 and s == sid and m == PLANE_MODE_RTL for t, s, m in modes)
        assert not any(t < asked - 1 and s == sid and m == PLANE_MODE_RTL for t, s, m in modes)


def confirm(page, action_button: str) -> dict:
    """Click an action, confirm it in the dialog, and return the server's answer."""
    count = page.evaluate("() => operatorActions.answers.length")
    page.click(action_button)
    page.wait_for_selector("#operator-confirm[open]")
    page.click("#operator-ok")
    page.wait_for_function(f"() => operatorActions.answers.length > {count}", timeout=60_000)
    last = page.evaluate("() => operatorActions.last")
    assert last["code"] == 200, last
    return last["answer"]


def check_header_layout(page) -> None:
    """With the action buttons and their status in the header, the phase line is whole at
    1920 and 1280 wide; at 390 the actions come below the map and the player, and nothing is
    wider than the window."""
    geometry = (
        "() => { const box = id => document.getElementById(id).getBoundingClientRect(),"
        " p = document.getElementById('phase'); return {cut: p.scrollWidth > p.clientWidth,"
        " phase: p.textContent, map: box('map').bottom, player: box('play').bottom,"
        " actions: [box('operator-actions').top, box('operator-actions').left,"
        " box('operator-actions').right], page: document.documentElement.scrollWidth}; }"
    )
    for width, height in ((1920, 1080), (1280, 720)):
        page.set_viewport_size({"width": width, "height": height})
        at = page.evaluate(geometry)
        assert at["phase"] and not at["cut"] and at["page"] <= width, (width, at)
    page.set_viewport_size({"width": 390, "height": 844})
    at = page.evaluate(geometry)
    top, left, right = at["actions"]
    assert top >= at["map"] and top >= at["player"] and left >= 0 and right <= 390, at
    assert at["page"] <= 390, at
    page.set_viewport_size({"width": 1280, "height": 800})


def live_step(page) -> int:
    return page.evaluate("() => missionView.steps.length ? missionView.steps.at(-1).step : -1")


@pytest.mark.timeout(240)
def test_an_operator_flies_the_mission_from_the_page(page_demo):
    demo, browser = page_demo
    readonly = browser.new_page()
    readonly.goto(demo.base)  # without the token: read-only, and says so
    readonly.wait_for_function("() => window.operatorActions && operatorActions.reason !== ''")
    assert "read-only" in readonly.inner_text("#operator-actions")
    assert readonly.is_disabled("#operator-actions button[data-action=end]")
    readonly.close()

    page = browser.new_page(viewport={"width": 1280, "height": 800})
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(demo.url)
    page.wait_for_function("() => operatorActions.enabled", timeout=30_000)
    page.wait_for_function("() => missionView.steps.length >= 2", timeout=60_000)

    page.click("button[data-action=mark]")
    page.fill("#operator-cell-x", "50")
    page.fill("#operator-cell-y", "50")
    page.click("#operator-cancel")  # asked, then cancelled: nothing sent
    answer = confirm(page, "button[data-action=mark]")  # the cell is still filled in
    assert "taken in by every UAV" in answer["result"]

    answer = confirm(page, "button[data-action=hold]")
    held_at, held_s = answer["step"], time.time()
    page.wait_for_function(f"() => missionView.steps.at(-1).step >= {held_at + 5}")
    resumed_s = time.time()
    answer = confirm(page, "button[data-action=resume]")
    assert answer["step"] >= held_at + 5

    page.click('#vehicles tbody tr[data-uav="1"]')  # the page's vehicle panel: swarm:select
    assert page.inner_text("#vehicle-actions button[data-action=rtl]") == "RTL UAV 2"
    answer = confirm(page, "#vehicle-actions button[data-action=rtl]")
    assert "RTL accepted by vehicle 2" in answer["result"]
    page.wait_for_function(
        "() => { const v = missionView.steps.at(-1).vehicles;"
        " return v[1].mode === 'RTL' && v[0].mode === 'GUIDED'; }",
        timeout=60_000,
    )
    # sent home by the operator, not lost: in the table and in its panel
    page.wait_for_function(
        "() => document.querySelector('#vehicles tr[data-uav=\"1\"] td.link')"
        ".textContent.startsWith('sent home (operator)')", timeout=30_000,
    )  # fmt: skip
    assert "LOST" not in page.inner_text("#vehicles")
    assert page.inner_text('#vp-fields dd[data-field="state"]') == "sent home (operator)"
    check_header_layout(page)
    page.wait_for_function(
        "() => missionView.events.filter(e => e.kind === 'operator').length >= 4", timeout=30_000
    )
    answer = confirm(page, "button[data-action=end]")
    assert live_step(page) < STEPS
    assert not errors, errors

    result = demo.result()
    assert result["ended"].startswith("completed early: ended by the operator")
    assert result["steps"] < STEPS
    actions = result["operator_actions"]
    assert [a["action"] for a in actions] == ["mark", "hold", "resume", "rtl", "end"]
    assert all(a["who"] == "127.0.0.1" and utc_s(a["time_utc"]) > 0 for a in actions)
    assert actions[0]["cell"] == [50, 50] and actions[3]["uav"] == 1
    assert result["operator_held_steps"] >= 5 and result["operator_refused"] == 0

    # held: not one guided target sent; searching: they are
    tlog = demo.out / "mission.tlog"
    sent = repositions(tlog)
    assert not [t for t in sent if held_s <= t <= resumed_s]
    assert len([t for t in sent if t > resumed_s]) > 0
    # RTL one: vehicle 2's heartbeats say RTL before the mission's end, vehicle 1's do not
    ended_s = utc_s(actions[4]["time_utc"])
    modes = [(s, m) for t, s, m in heartbeats(tlog) if t < ended_s]
    assert (2, PLANE_MODE_RTL) in modes and (1, PLANE_MODE_RTL) not in modes
