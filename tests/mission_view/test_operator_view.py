"""The operator's side of the mission view in headless Chromium, over one lockstep demo
(paper-2uav) that is killed with SIGKILL half-way: the phase line through the launch and the
search, the vehicle panel, the disconnected banner with growing link ages after the server dies,
then ``swarmplan view`` of the cut-short replay: it opens at step 0, plays, says where it was
cut, and lays out at 390 px wide; and with ``--tiles`` over a tile server of the test's own. The
cursor readout and the distance measure are checked in both map frames (the mission frame, and
Web Mercator under tiles). Without ``--tiles`` no request leaves the page's own server. ~45 s;
skipped, saying why, where Chromium is missing."""

from __future__ import annotations

import math
import os
import re
import signal
import struct
import subprocess
import sys
import threading
import time
import zlib
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from browser import wait_for_url
from loopback import REPO, env, start_swarmplan, stop

from planner.geodesy import local_km_to_geodetic
from planner.scenario import load_scenario

STEPS = 60
KILL_AT = 12
SCENARIO = "paper-2uav"
# one demo for the module (the fixture below): its tests on one worker of pytest-xdist, in order
pytestmark = pytest.mark.xdist_group("operator-view")


def open_page(chromium, url: str, width: int = 1280, height: int = 800):
    """The page at ``url`` once it has its layout: (page, console errors, every URL it asked
    for: documents, scripts, images, tiles)."""
    page = chromium.new_page(viewport={"width": width, "height": height})
    errors: list[str] = []
    asked: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("request", lambda r: asked.append(r.url))
    page.goto(url)
    page.wait_for_function("() => window.missionView && missionView.layout !== null")
    return page, errors, asked


def only_from(base: str, asked: list[str]) -> list[str]:
    """The requests of ``asked`` that left the page's own server (none, for a page without
    --tiles)."""
    return [u for u in asked if not (u.startswith(base) or u.startswith("data:"))]


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
        url = wait_for_url(log, 60, demo)
        page, errors, asked = open_page(chromium, url)
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
        assert only_from(url, asked) == [], asked
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
        url = wait_for_url(log, 30, server)
        page, errors, asked = open_page(chromium, url, 390, 844)
        page.wait_for_function("() => missionView.current === 0")
        assert page.inner_text("#phase").startswith("search")
        last = page.evaluate("() => missionView.steps[missionView.steps.length - 1].step")
        assert 0 < last < STEPS  # (the last steps may be in gzip's buffer when killed)
        assert page.inner_text("#endmark").startswith(f"cut short at step {last} of {STEPS}")
        # 2 steps a second: the pause lands well before the end of the cut replay (~9 steps),
        # where a click on the button would play it again from the start
        page.select_option("#speed", "2")
        page.click("#play")
        page.wait_for_function("() => missionView.current >= 2", timeout=10_000)
        page.click("#play")  # pause
        assert page.evaluate("() => missionView.playing") is None
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
        check_cursor_and_measure(page)
        assert only_from(url, asked) == [], asked  # no --tiles: nothing asked of any network
        assert not errors, errors
        page.close()
    finally:
        assert stop(server, timeout_s=15) in (0, None)  # (SIGTERM: a loaded machine is slow)


# ------------------------------------------------------------------ cursor readout and measure

#: "35.18294°S 149.27502°E · x 10.00 km, y 20.00 km"
CURSOR = re.compile(r"([\d.]+)°([NS]) ([\d.]+)°([EW]) · x (-?[\d.]+) km, y (-?[\d.]+) km")


def map_pixel(page, x_km: float, y_km: float) -> tuple[float, float]:
    """Where the mission-frame point is on the screen (the page's own placement, as its
    vehicles are drawn)."""
    return tuple(page.evaluate(
        "([x, y]) => { const p = missionView.map.latLngToContainerPoint(pt(x, y)),"
        " r = document.getElementById('map').getBoundingClientRect();"
        " return [r.left + p.x, r.top + p.y]; }", [x_km, y_km],
    ))  # fmt: skip


def clear_points(page, count: int) -> list[tuple[float, float]]:
    """``count`` points of the area (km) at least 8 km from every vehicle drawn (a marker takes
    the mouse's events itself)."""
    drawn = page.evaluate("() => missionView.steps[missionView.current].vehicles"
                          ".map(v => [v.x_km, v.y_km])")  # fmt: skip
    candidates = [(20.0, 30.0), (80.0, 70.0), (30.0, 80.0), (70.0, 20.0), (50.0, 90.0)]
    clear = [c for c in candidates if all(math.dist(c, v) > 8 for v in drawn)]
    assert len(clear) >= count, drawn
    return clear[:count]


def check_cursor_and_measure(page) -> None:
    """Under the mouse, the readout gives the point's mission km and its lat/lon as
    ``planner.geodesy`` converts them; two clicks of the measure give distance and bearing."""
    origin = load_scenario(SCENARIO).origin
    km_per_px = page.evaluate(
        "() => { const m = missionView.map, c = m.getSize().divideBy(2),"
        " a = toKm(m.containerPointToLatLng(c)), b = toKm(m.containerPointToLatLng(c.add([1, 0])));"
        " return Math.hypot(b[0] - a[0], b[1] - a[1]); }"
    )
    first, second = clear_points(page, 2)
    page.mouse.move(*map_pixel(page, *first))
    text = page.inner_text("#cursor")
    found = CURSOR.fullmatch(text)
    assert found, text
    lat = float(found[1]) * (1 if found[2] == "N" else -1)
    lon = float(found[3]) * (1 if found[4] == "E" else -1)
    x, y = float(found[5]), float(found[6])
    assert math.dist((x, y), first) < 2 * km_per_px + 0.01, (text, first, km_per_px)
    want_lat, want_lon = (float(c[0]) for c in local_km_to_geodetic(x, y, origin))
    assert abs(lat - want_lat) < 1e-4 and abs(lon - want_lon) < 1e-4, (text, want_lat, want_lon)

    page.click("#measure")
    assert page.inner_text("#measure-text") == "click two points on the map"
    for point in (first, second):
        page.mouse.click(*map_pixel(page, *point))
    text = page.inner_text("#measure-text")
    found = re.fullmatch(r"([\d.]+) km, bearing (\d+)°", text)
    assert found, text
    dx, dy = second[0] - first[0], second[1] - first[1]
    bearing = math.degrees(math.atan2(dx, dy)) % 360
    assert abs(float(found[1]) - math.hypot(dx, dy)) < 3 * km_per_px + 0.01, text
    assert abs((int(found[2]) - bearing + 180) % 360 - 180) <= 1.5, (text, bearing)
    page.keyboard.press("Escape")  # the measure off again
    assert page.get_attribute("#measure", "aria-pressed") == "false"


# ------------------------------------------------------------------ a tile server of our own


def solid_png(rgb: tuple[int, int, int], size: int = 256) -> bytes:
    """A ``size`` x ``size`` PNG of one colour."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    rows = b"".join(b"\x00" + bytes(rgb) * size for _ in range(size))
    header = struct.pack(">IIBBBBB", size, size, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows)) + \
        chunk(b"IEND", b"")  # fmt: skip


class TileServer:
    """An XYZ tile server on 127.0.0.1 (a free port): every /tile/{z}/{x}/{y}.png is one
    light-green tile; the tiles asked for are kept as (z, x, y)."""

    TILE = solid_png((200, 230, 200))

    def __init__(self) -> None:
        self.asked: list[tuple[int, int, int]] = []
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                found = re.fullmatch(r"/tile/(\d+)/(\d+)/(\d+)\.png", self.path)
                if not found:
                    self.send_error(404)
                    return
                server.asked.append(tuple(int(g) for g in found.groups()))
                self.send_response(200)
                self.send_header("Content-Type", "image/png")
                self.send_header("Content-Length", str(len(server.TILE)))
                self.end_headers()
                self.wfile.write(server.TILE)

            def log_message(self, *args) -> None:
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.template = f"http://127.0.0.1:{self.httpd.server_port}/tile/{{z}}/{{x}}/{{y}}.png"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def tile_of(lat: float, lon: float, z: int) -> tuple[int, int]:
    """The XYZ (slippy map) tile holding lat/lon at zoom ``z``."""
    n = 2**z
    x = int((lon + 180) / 360 * n)
    y = int((1 - math.asinh(math.tan(math.radians(lat))) / math.pi) / 2 * n)
    return x, y


@pytest.mark.timeout(120)
def test_tiles_drawn_under_the_mission(chromium, killed_demo):
    """``swarmplan view --tiles`` over the test's tile server: the page asks it for the tiles
    of the mission area (z/x/y: the area's centre and corners among them), draws them in
    Leaflet's tile pane under the heat layer and the vehicles, and the cursor readout and the
    measure stay right in Web Mercator."""
    _, _, _, out = killed_demo
    tiles = TileServer()
    log = out / "view-tiles.log"
    server = start_swarmplan(["view", str(out), "--tiles", tiles.template], log)
    try:
        url = wait_for_url(log, 30, server)
        page, errors, asked = open_page(chromium, url)
        page.wait_for_function(  # every tile of the view in
            "() => { const t = document.querySelectorAll('.leaflet-tile-pane img.leaflet-tile');"
            " return t.length > 0 && Array.from(t).every(i => i.classList.contains("
            "'leaflet-tile-loaded')); }", timeout=15_000,
        )  # fmt: skip
        assert tiles.asked, "no tile asked for"
        zooms = {z for z, _, _ in tiles.asked}
        assert len(zooms) == 1, tiles.asked
        z = zooms.pop()
        scenario = load_scenario(SCENARIO)
        w, h = scenario.config.area_km
        for x_km, y_km in ((w / 2, h / 2), (0, 0), (w, h)):
            lat, lon = (float(c[0]) for c in local_km_to_geodetic(x_km, y_km, scenario.origin))
            assert (z, *tile_of(lat, lon, z)) in tiles.asked, (x_km, y_km, tiles.asked)
        drawn = page.evaluate(
            "() => Array.from(document.querySelectorAll('.leaflet-tile-pane img.leaflet-tile'))"
            ".filter(i => i.complete && i.naturalWidth === 256).map(i => i.src)"
        )
        assert drawn and all(src.startswith(tiles.template.split("/tile/")[0]) for src in drawn)
        under = page.evaluate(
            "() => ['tile', 'overlay', 'marker'].map(p => Number(getComputedStyle("
            "missionView.map.getPane(p + 'Pane')).zIndex))"
        )
        assert under[0] < under[1] < under[2], under  # tiles, then the heat layer, then UAVs
        assert page.query_selector(".leaflet-overlay-pane #heat-canvas") is not None
        assert set(only_from(url, asked)) == {
            u for u in asked if u.startswith(tiles.template.split("/tile/")[0])
        }  # the only requests elsewhere are the tiles
        check_cursor_and_measure(page)
        assert not errors, errors
        page.close()
    finally:
        tiles.close()
        assert stop(server, timeout_s=15) in (0, None)  # (SIGTERM: a loaded machine is slow)
