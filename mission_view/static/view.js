// The mission view page: one WebSocket (/ws) brings the mission's layout, its steps, its phase
// lines and the heat layer asked for. The map is Leaflet (vendored): without --tiles in the
// mission frame (L.CRS.Simple, 1 unit = 1 m, x east, y north from the area's south-west corner);
// with --tiles in Web Mercator over the tile server, the mission frame converted through the
// layout's geo_grid. Works the same live and in a replay. panel.js adds the vehicle panel, the
// cursor readout and the distance measure.
"use strict";

const TRAIL_STEPS = 30;
const PALETTE = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2",
  "#17becf", "#bcbd22", "#393b79", "#637939", "#ad494a", "#7b4173", "#3182bd", "#e6550d",
  "#31a354", "#756bb1", "#636363", "#843c39", "#5254a3"];
const KIND_NAMES = { engagement: "engagements", miss: "misses", override: "envelope",
  refusal: "refused", warning: "warnings", link: "link", phase: "phase", operator: "operator" };
const RECONNECT_MAX_S = 10;

const view = {
  layout: null, steps: [], events: [], phases: [], current: -1, follow: true, ended: false,
  kind: "coverage", uav: 0, layerStep: null, layerKind: null, layerUav: null, layerCount: 0,
  map: null, ws: null, vehicles: [], heatCanvas: null, selected: null, restore: null,
  renderedSteps: [],  // every step shown while following the mission live
  hiddenKinds: new Set(), timelineKey: "",
  conn: { state: "connecting", attempts: 0, lostAt: null, lastMessageAt: 0, retryAt: 0,
    resumeFollow: false },
  playing: null,  // the player's interval id
};
window.missionView = view;  // read by the browser tests and by panel.js / actions.js

const $ = (id) => document.getElementById(id);
const colour = (i) => PALETTE[i % PALETTE.length];

// ------------------------------------------------------------------ mission frame <-> map

// lat/lon of a mission-frame point, bilinear in the layout's geo_grid (linear beyond it)
function kmToGeo(x, y) {
  const g = view.layout.geo_grid, xs = g.x_km, ys = g.y_km;
  const cell = (v, a) => Math.min(Math.max(0, a.findIndex((t) => t > v) - 1), a.length - 2);
  const i = cell(x, xs), j = cell(y, ys);
  const fx = (x - xs[i]) / (xs[i + 1] - xs[i]), fy = (y - ys[j]) / (ys[j + 1] - ys[j]);
  const mix = (m) => (1 - fx) * (1 - fy) * m[i][j] + fx * (1 - fy) * m[i + 1][j] +
    (1 - fx) * fy * m[i][j + 1] + fx * fy * m[i + 1][j + 1];
  return [mix(g.lat), mix(g.lon)];
}

// the mission-frame point of a lat/lon (Newton's method on kmToGeo)
function geoToKm(lat, lon) {
  let x = view.layout.area_km[0] / 2, y = view.layout.area_km[1] / 2;
  for (let n = 0; n < 6; n++) {
    const [la, lo] = kmToGeo(x, y), [lax, lox] = kmToGeo(x + 0.01, y), [lay, loy] = kmToGeo(x, y + 0.01);
    const a = (lax - la) / 0.01, b = (lay - la) / 0.01, c = (lox - lo) / 0.01, d = (loy - lo) / 0.01;
    const det = a * d - b * c, r1 = lat - la, r2 = lon - lo;
    x += (d * r1 - b * r2) / det; y += (a * r2 - c * r1) / det;
  }
  return [x, y];
}

function pt(x, y) {
  if (view.layout && view.layout.tiles) return L.latLng(...kmToGeo(x, y));
  return L.latLng(y * 1000, x * 1000);
}

function toKm(latlng) {
  if (view.layout.tiles) return geoToKm(latlng.lat, latlng.lng);
  return [latlng.lng / 1000, latlng.lat / 1000];
}

// ------------------------------------------------------------------ colour ramps

function ramp(stops) {
  const lut = new Uint8ClampedArray(256 * 4);
  for (let v = 0; v < 256; v++) {
    const t = v / 255;
    let k = 0;
    while (k < stops.length - 2 && t > stops[k + 1][0]) k++;
    const [t0, c0] = stops[k], [t1, c1] = stops[k + 1];
    const f = Math.min(1, Math.max(0, (t - t0) / (t1 - t0)));
    for (let c = 0; c < 4; c++) lut[v * 4 + c] = c0[c] + f * (c1[c] - c0[c]);
  }
  return lut;
}
const RAMPS = {
  coverage: ramp([[0, [0, 120, 110, 0]], [1, [0, 120, 110, 150]]]),
  tpm: ramp([[0, [20, 10, 60, 0]], [0.2, [60, 15, 110, 40]], [0.5, [180, 40, 90, 130]],
    [0.8, [245, 120, 30, 190]], [1, [252, 230, 60, 230]]]),
  pheromone: ramp([[0, [255, 255, 255, 0]], [1, [40, 110, 30, 120]]]),
};

function drawLegend() {
  const canvas = $("legend-bar"), ctx = canvas.getContext("2d");
  const lut = RAMPS[view.kind], img = ctx.createImageData(canvas.width, canvas.height);
  for (let x = 0; x < canvas.width; x++) {
    const v = Math.round(255 * x / (canvas.width - 1));
    for (let y = 0; y < canvas.height; y++) {
      const o = (y * canvas.width + x) * 4;
      for (let c = 0; c < 3; c++) img.data[o + c] = lut[v * 4 + c];
      img.data[o + 3] = Math.max(lut[v * 4 + 3], 40);
    }
  }
  ctx.putImageData(img, 0, 0);
  const who = view.kind === "coverage" ? "swarm" : `UAV ${view.uav + 1}`;
  $("legend-text").textContent = `${who}: ${view.layout.layer_scales[view.kind]}`;
}

// ------------------------------------------------------------------ map

const quiet = { interactive: false, keyboard: false };  // decorations: no pointer, no Tab stop

function initMap(layout) {
  const [w, h] = layout.area_km;
  const corners = [pt(0, 0), pt(w, 0), pt(w, h), pt(0, h)];
  const map = layout.tiles
    ? L.map("map", { zoomSnap: 0.25, attributionControl: false })
    : L.map("map", { crs: L.CRS.Simple, minZoom: -14, maxZoom: 3, zoomSnap: 0.25,
      attributionControl: false });
  if (layout.tiles) L.tileLayer(layout.tiles, { maxZoom: 19 }).addTo(map);
  map.fitBounds(L.latLngBounds(corners).pad(0.04));
  L.control.scale({ imperial: false, maxWidth: 160 }).addTo(map);
  view.map = map;

  const canvas = document.createElement("canvas");
  [canvas.width, canvas.height] = layout.layer_shape;
  canvas.className = "heat";
  canvas.id = "heat-canvas";
  view.heatCanvas = canvas;
  const [bx, by] = layout.layer_shape;
  const block = Math.max(w / layout.cell_km / bx, h / layout.cell_km / by) * layout.cell_km;
  L.svgOverlay(canvas, L.latLngBounds(pt(0, 0), pt(bx * block, by * block)),
    { interactive: false }).addTo(map);

  L.polygon(corners, { fill: false, color: "#333", weight: 1, interactive: false }).addTo(map);
  for (const line of layout.graticule) {
    const pts = line.points.map(([x, y]) => pt(x, y));
    L.polyline(pts, { color: "#999", weight: 0.7, dashArray: "3 4", interactive: false }).addTo(map);
    L.marker(pts[0], { ...quiet, icon: L.divIcon({ className: "grid-label",
      html: line.label, iconSize: null, iconAnchor: line.axis === "lat" ? [52, 6] : [18, -4] }) })
      .addTo(map);
  }
  for (const t of layout.threats) {
    L.circle(pt(t.x_km, t.y_km), { radius: t.radius_km * 1000, color: "#b30000", weight: 1.5,
      fillColor: "#e34a33", fillOpacity: 0.12 })
      .bindTooltip(`threat zone, radius ${t.radius_km} km`).addTo(map);
  }
  view.engagedLayer = L.layerGroup().addTo(map);
  view.truthLayer = L.layerGroup().addTo(map);
  view.homeLayer = L.layerGroup().addTo(map);
  for (let i = 0; i < layout.uav_count; i++) addVehicle(map, i);
  if (!layout.truth) {
    $("show-truth").parentElement.style.display = "none";
    $("truth-legend").style.display = "none";
  }
  // the map's drawings are pictures, not controls: out of the accessibility tree
  for (const svg of document.querySelectorAll("#map svg")) {
    svg.setAttribute("aria-hidden", "true");
    svg.setAttribute("focusable", "false");
  }
}

function addVehicle(map, i) {
  const trail = L.polyline([], { color: colour(i), weight: 2, opacity: 0.8, interactive: false })
    .addTo(map);
  const leg = L.polyline([], { color: colour(i), weight: 1, dashArray: "4 4", opacity: 0.9,
    interactive: false }).addTo(map);
  const target = L.circleMarker(pt(0, 0), { radius: 3, color: colour(i), weight: 1.5,
    fill: false, opacity: 0 }).bindTooltip(`UAV ${i + 1}: guided target`).addTo(map);
  const icon = L.divIcon({ className: "uav-icon", iconSize: [16, 16], iconAnchor: [8, 8],
    html: `<svg width="16" height="16" viewBox="-8 -8 16 16" aria-hidden="true"><path d="M7,0 L-6,-5 L-3,0 L-6,5 Z"
      fill="${colour(i)}" stroke="white" stroke-width="1"/></svg><span>${i + 1}</span>` });
  // not on the map until its first step: no arrows piled at the area's corner
  const marker = L.marker(pt(0, 0), { icon, keyboard: false, title: `UAV ${i + 1}` });
  marker.on("click", () => selectVehicle(i));
  view.vehicles.push({ trail, leg, target, marker, home: null });
}

function drawHeat(msg) {
  const canvas = view.heatCanvas;
  if (!canvas) return;
  const [bx, by] = msg.shape;
  const raw = atob(msg.data), ctx = canvas.getContext("2d");
  const img = ctx.createImageData(bx, by), lut = RAMPS[msg.kind];
  for (let ix = 0; ix < bx; ix++) {
    for (let iy = 0; iy < by; iy++) {
      const v = raw.charCodeAt(ix * by + iy), o = ((by - 1 - iy) * bx + ix) * 4;
      img.data[o] = lut[v * 4]; img.data[o + 1] = lut[v * 4 + 1];
      img.data[o + 2] = lut[v * 4 + 2]; img.data[o + 3] = lut[v * 4 + 3];
    }
  }
  ctx.putImageData(img, 0, 0);
  view.layerStep = msg.step; view.layerKind = msg.kind; view.layerUav = msg.uav;
  view.layerCount += 1;
}

// ------------------------------------------------------------------ one step on the page

function fmt(v, digits = 0) { return v === null || v === undefined ? "–" : v.toFixed(digits); }

function render(k) {
  const s = view.steps[k];
  if (!s) return;
  view.current = k;
  if (view.follow) view.renderedSteps.push(s.step);
  document.body.dataset.step = String(s.step);
  s.vehicles.forEach((v, i) => drawVehicle(k, v, i));
  drawEngaged(k);
  drawTruth(s);
  untabMapShapes();
  drawHeader();
  drawTable();
  drawTimeline();
  const slider = $("slider");
  slider.max = String(view.steps.length - 1);
  slider.value = String(k);
  $("slider-label").textContent = `step ${s.step}` +
    (view.layout.step_s ? ` (${Math.round(s.step * view.layout.step_s)} s simulated)` : "");
  if (window.drawVehiclePanel) window.drawVehiclePanel();
}

function drawVehicle(k, v, i) {
  const g = view.vehicles[i];
  if (!g) return;
  if (!view.map.hasLayer(g.marker)) {
    g.marker.addTo(view.map);
    g.marker.getElement().dataset.uav = String(i);
  }
  g.marker.setLatLng(pt(v.x_km, v.y_km));
  const el = g.marker.getElement();
  el.querySelector("svg").style.transform = `rotate(${-v.heading_deg}deg)`;
  el.classList.toggle("lost", !v.active);
  el.classList.toggle("selected", view.selected === i);
  const from = Math.max(0, k - TRAIL_STEPS);
  g.trail.setLatLngs(view.steps.slice(from, k + 1).map((t) => pt(t.vehicles[i].x_km,
    t.vehicles[i].y_km)));
  if (v.target_km && v.active && !v.done) {
    g.target.setLatLng(pt(...v.target_km)).setStyle({ opacity: 1 });
    g.leg.setLatLngs([pt(v.x_km, v.y_km), pt(...v.target_km)]);
  } else {
    g.target.setStyle({ opacity: 0 });
    g.leg.setLatLngs([]);
  }
  drawHome(i, v.home_km);
}

function drawHome(i, home) {
  const g = view.vehicles[i];
  const key = home ? home.join(",") : "";
  if (!home || g.homeKey === key) return;
  g.homeKey = key;
  if (g.home) view.homeLayer.removeLayer(g.home);
  g.home = L.marker(pt(...home), { ...quiet, icon: L.divIcon({ className: "home-icon",
    iconSize: [12, 12], iconAnchor: [6, 6], html: `<svg width="12" height="12" viewBox="-6 -6 12 12" aria-hidden="true">` +
    `<path d="M-5,5 L-5,-1 L0,-5 L5,-1 L5,5 Z" fill="white" stroke="${colour(i)}" stroke-width="1.5"/></svg>` }) })
    .addTo(view.homeLayer);
}

// the phase line that held at step `step` (the newest one from a step at or before it)
function phaseAt(step) {
  let text = "";
  for (const p of view.phases) if (p.step <= step) text = p.text;
  return text;
}

function drawHeader() {
  const L_ = view.layout, s = view.steps[view.current];
  const newest = view.steps[view.steps.length - 1];
  const following = view.follow || !L_.live || view.ended;
  const phase = !s || (view.follow && !view.ended)
    ? (view.phases.length ? view.phases[view.phases.length - 1].text : "")
    : phaseAt(s.step);
  $("phase").textContent = phase;
  $("phase").title = `mission phase at the step shown: ${phase}`;
  if (!s) return;
  $("stepinfo").textContent = `step ${s.step} / ${L_.steps}`;
  const behind = newest.step - s.step;
  $("liveinfo").textContent = following || behind <= 0 ? "" : `live: step ${newest.step} (${behind} behind)`;
  $("endmark").textContent = endMark();
  const late = $("lateness");
  late.textContent = L_.source === "mavlink" ? `late steps ${s.late_steps}${s.late ? " (this one late)" : ""}` : "";
  late.classList.toggle("late", s.late);
  $("totals").textContent = `coverage ${(100 * s.coverage).toFixed(1)} %, engaged ${s.engaged}` +
    ` (value ${fmt(s.engaged_value, 0)})`;
}

// "cut short at step 99 of 250" (a replay with no end line), "ended early at step 40 of 250"
function endMark() {
  const L_ = view.layout, last = view.steps[view.steps.length - 1];
  if (!view.ended || !last) return "";
  if (L_.cut_short) return `cut short at step ${last.step} of ${L_.steps} (the recording stops there)`;
  if (last.step < L_.steps) return `ended early at step ${last.step} of ${L_.steps}`;
  return "";
}

// how long the page has had no word from the server (s), 0 while connected
function staleSeconds() {
  if (view.conn.state === "connected" || view.ended || !view.conn.lastMessageAt) return 0;
  return (performance.now() - view.conn.lastMessageAt) / 1000;
}

function drawTable() {
  const s = view.steps[view.current];
  if (!s) return;
  const newest = view.current === view.steps.length - 1, stale = newest ? staleSeconds() : 0;
  const rows = s.vehicles.map((v, i) => {
    const lost = !v.active && !v.done;
    const age = v.last_heard_s === null ? null : v.last_heard_s + stale;
    const link = age === null ? "–" : lost ? `LOST ${fmt(age, 1)} s` :
      stale ? `${fmt(age, 1)} s?` : `${fmt(age, 1)} s`;
    const signed = v.signed === null ? "–" : v.signed ? "yes" : "no";
    const cls = [lost ? "lost" : "", stale ? "stale" : ""].join(" ").trim();
    return `<tr data-uav="${i}" tabindex="0" class="${view.selected === i ? "selected" : ""}">` +
      `<td><span class="swatch" style="background:${colour(i)}"></span>${i + 1}</td>` +
      `<td>${v.mode || "–"}</td><td>${v.planner_mode || "–"}</td>` +
      `<td>${fmt(v.ground_speed_mps)} / ${fmt(v.airspeed_mps)}</td>` +
      `<td class="link ${cls}"${stale ? ' title="no word from the server: older than this"' : ""}>${link}</td><td>${signed}</td></tr>`;
  });
  const body = $("vehicles").tBodies[0], focused = document.activeElement;
  const refocus = focused && body.contains(focused) ? focused.dataset.uav : null;
  body.innerHTML = rows.join("");
  if (refocus !== null) body.querySelector(`tr[data-uav="${refocus}"]`).focus({ preventScroll: true });
}

function drawEngaged(k) {
  const layer = view.engagedLayer;
  layer.clearLayers();
  for (const e of view.events) {
    if (e.step > view.steps[k].step) break;
    if (e.kind !== "engagement" || e.x_km === null) continue;
    const id = (e.text.match(/target (\d+)/) || [])[1] || "";
    L.marker(pt(e.x_km, e.y_km), { keyboard: false, icon: L.divIcon({ className: "engaged-icon", iconSize: [18, 18],
      iconAnchor: [9, 9], html: `<span class="star">&#9733;</span><span class="engaged-label">${id}</span>` }) })
      .bindTooltip(`step ${e.step}, UAV ${e.uav + 1}: ${e.text}`).addTo(layer);
  }
}

// Leaflet makes shapes with a tooltip focusable: they are pictures, reached by mouse only
function untabMapShapes() {
  for (const el of document.querySelectorAll("#map path[tabindex]")) el.setAttribute("tabindex", "-1");
}

function drawTruth(s) {
  const layer = view.truthLayer;
  layer.clearLayers();
  if (!s.truth || !$("show-truth").checked) return;
  for (const [id, x, y, alive] of s.truth) {
    L.circleMarker(pt(x, y), { radius: 5, color: alive ? "#000" : "#888", weight: 1.5,
      fill: false, dashArray: alive ? null : "2 2", className: "truth" })
      .bindTooltip(`truth: target ${id}${alive ? "" : " (serviced)"} — ground truth, not known to the swarm`)
      .addTo(layer);
  }
}

// ------------------------------------------------------------------ the timeline

function shownEvents() { return view.events.filter((e) => !view.hiddenKinds.has(e.kind)); }

function drawFilter() {
  const counts = {};
  for (const e of view.events) counts[e.kind] = (counts[e.kind] || 0) + 1;
  const box = $("timeline-filter");
  for (const kind of Object.keys(counts)) {
    let input = box.querySelector(`input[data-kind="${kind}"]`);
    if (!input) {
      const label = document.createElement("label");
      label.className = `chip ${kind}`;
      label.innerHTML = `<input type="checkbox" data-kind="${kind}" checked> <span></span>`;
      box.appendChild(label);
      input = label.querySelector("input");
      input.addEventListener("change", () => {
        if (input.checked) view.hiddenKinds.delete(kind); else view.hiddenKinds.add(kind);
        drawTimeline();
      });
    }
    input.nextElementSibling.textContent = `${KIND_NAMES[kind] || kind} ${counts[kind]}`;
  }
}

// every event known, newest first (those after the step shown are greyed): jump by clicking
// or by Enter on one
function drawTimeline() {
  const s = view.steps[view.current];
  if (!s) return;
  const shown = shownEvents();
  const key = `${view.events.length}|${[...view.hiddenKinds].join(",")}`;
  const list = $("timeline");
  if (key !== view.timelineKey) {
    view.timelineKey = key;
    drawFilter();
    const focused = list.contains(document.activeElement) ? document.activeElement.dataset.n : null;
    list.innerHTML = shown.slice(-400).reverse().map((e) =>
      `<li class="${e.kind}" value="${e.step}"><button type="button" data-step="${e.step}" data-n="${view.events.indexOf(e)}">` +
      `${e.uav === null || e.uav === undefined ? "" : `UAV ${e.uav + 1}: `}${escapeHtml(e.text)}</button></li>`).join("");
    if (focused !== null) {
      const again = list.querySelector(`button[data-n="${focused}"]`);
      if (again) again.focus({ preventScroll: true });
    }
  }
  for (const li of list.children) li.classList.toggle("ahead", Number(li.value) > s.step);
}

function escapeHtml(text) {
  return String(text).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" })[c]);
}

function showStep(k) {
  k = Math.max(0, Math.min(view.steps.length - 1, k));
  const newest = k === view.steps.length - 1 && view.layout.live && !view.ended &&
    view.conn.state === "connected";
  setFollow(newest);
  render(k);
  ask();
}

function jumpToStep(step) {
  const k = view.steps.findIndex((s) => s.step === step);
  if (k >= 0) { stopPlaying(); setFollow(false); render(k); ask(); }
}

function jumpEvent(direction) {
  const here = view.steps[view.current].step;
  const steps = shownEvents().map((e) => e.step);
  const next = direction > 0 ? steps.find((t) => t > here) : steps.reverse().find((t) => t < here);
  if (next !== undefined) jumpToStep(next);
}

// ------------------------------------------------------------------ the player

function stopPlaying() {
  if (view.playing !== null) clearInterval(view.playing);
  view.playing = null;
  $("play").textContent = "play";
}

function play() {
  if (view.playing !== null) { stopPlaying(); return; }
  if (view.current >= view.steps.length - 1) showStep(0);
  $("play").textContent = "pause";
  view.playing = setInterval(() => {
    if (view.current >= view.steps.length - 1) { stopPlaying(); return; }
    showStep(view.current + 1);
  }, 1000 / Number($("speed").value));
}

// ------------------------------------------------------------------ talking to the server

function ask() {
  if (!view.ws || view.ws.readyState !== WebSocket.OPEN) return;
  const step = view.follow ? null : (view.steps[view.current] || {}).step ?? null;
  view.ws.send(JSON.stringify({ type: "view", kind: view.kind, uav: view.uav, step }));
}

function setFollow(on) {
  view.follow = Boolean(on && view.layout && view.layout.live && !view.ended &&
    view.conn.state === "connected");
  $("follow").classList.toggle("active", view.follow);
  $("follow").setAttribute("aria-pressed", String(view.follow));
}

function onMission(msg) {
  if (view.layout) {  // a reconnection: the server sends everything again
    view.restore = view.follow ? null : (view.steps[view.current] || {}).step ?? null;
    view.steps = []; view.events = []; view.phases = []; view.timelineKey = "";
    view.layout = { ...msg };
    return;
  }
  view.layout = msg;
  initMap(msg);
  $("layer-uav").innerHTML = Array.from({ length: msg.uav_count }, (_, i) =>
    `<option value="${i}">UAV ${i + 1}</option>`).join("");
  $("title").textContent = `${msg.scenario}, seed ${msg.seed}, ` +
    (msg.live ? `live (${msg.source === "mavlink" ? "over MAVLink" : msg.source})` : `replay of ${msg.source === "mavlink" ? "a MAVLink mission" : "an offline run"}`);
  $("follow").style.display = msg.live ? "" : "none";
  setFollow(msg.live);
  drawLegend();
}

function onSteps(steps) {
  for (const s of steps) {
    view.steps.push(s);
    for (const e of s.events) view.events.push(e);
  }
  const restore = view.restore === null ? -1 : view.steps.findIndex((s) => s.step === view.restore);
  if (view.follow) render(view.steps.length - 1);
  else if (view.current < 0) render(view.layout.live ? view.steps.length - 1 : 0);  // a replay opens at its start
  else if (restore >= 0) { view.restore = null; render(restore); }  // after a reconnection
  else {
    $("slider").max = String(view.steps.length - 1);
    drawHeader();
  }
}

function onMessage(ev) {
  view.conn.lastMessageAt = performance.now();
  const msg = JSON.parse(ev.data);
  if (msg.type === "mission") onMission(msg);
  else if (msg.type === "steps") onSteps(msg.steps);
  else if (msg.type === "layer") drawHeat(msg);
  else if (msg.type === "phase") {
    view.phases.push({ step: msg.step ?? -1, text: msg.text });
    drawHeader();
  } else if (msg.type === "end") {
    view.ended = true;
    setFollow(false);
    drawHeader();
  }
}

function setConnection(state, text) {
  view.conn.state = state;
  $("connection").textContent = text;
  $("connection").className = state === "connected" ? "on" : "off";
}

function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  view.ws = ws;
  ws.onopen = () => {
    const again = view.conn.lostAt !== null;
    view.conn.attempts = 0; view.conn.lostAt = null;
    setConnection("connected", "connected");
    $("banner").hidden = true;
    document.body.classList.remove("disconnected");
    if (again && view.conn.resumeFollow) setFollow(true);
    ask();
  };
  ws.onmessage = onMessage;
  ws.onclose = () => {
    if (view.ws !== ws) return;
    if (view.ended) {
      setConnection("over", "mission over, disconnected");
      showBanner("info", view.layout && view.layout.live
        ? "The mission is over and its server has stopped: this is its last picture. " +
          "swarmplan view OUT shows it again." : "The view's server has stopped.");
      return;
    }
    if (view.conn.lostAt === null) {
      view.conn.lostAt = Date.now();
      view.conn.resumeFollow = view.follow;
    }
    setFollow(false);
    view.conn.attempts += 1;
    const wait = Math.min(RECONNECT_MAX_S, 2 ** (view.conn.attempts - 1));
    view.conn.retryAt = performance.now() + wait * 1000;
    setConnection("lost", "disconnected");
    document.body.classList.add("disconnected");
    setTimeout(connect, wait * 1000);
    tick();
  };
}

function showBanner(kind, text) {
  const banner = $("banner");
  banner.className = kind;
  banner.textContent = text;
  banner.hidden = false;
}

// once a second: the disconnected banner's clock and the vehicles' growing link ages
function tick() {
  const c = view.conn;
  if (c.state !== "lost") return;
  const since = new Date(c.lostAt).toLocaleTimeString();
  const ago = Math.round((Date.now() - c.lostAt) / 1000);
  const retry = Math.max(0, Math.ceil((c.retryAt - performance.now()) / 1000));
  const at = view.steps.length ? ` The picture is frozen at step ${view.steps[view.steps.length - 1].step}.` : "";
  showBanner("error", `Connection to the view's server lost at ${since} (${ago} s ago).${at} ` +
    `Reconnecting: attempt ${c.attempts + 1} ${retry ? `in ${retry} s` : "now"}.`);
  setConnection("lost", `disconnected, retrying (${c.attempts})`);
  drawTable();
  if (window.drawVehiclePanel) window.drawVehiclePanel();
}
setInterval(tick, 1000);

// ------------------------------------------------------------------ controls

$("slider").addEventListener("input", (e) => { stopPlaying(); setFollow(false); render(Number(e.target.value)); ask(); });
$("follow").addEventListener("click", () => { stopPlaying(); setFollow(true); render(view.steps.length - 1); ask(); });
$("step-back").addEventListener("click", () => { stopPlaying(); setFollow(false); showStep(view.current - 1); });
$("step-forward").addEventListener("click", () => { stopPlaying(); showStep(view.current + 1); });
$("play").addEventListener("click", play);
$("speed").addEventListener("change", () => { if (view.playing !== null) { stopPlaying(); play(); } });
$("prev-event").addEventListener("click", () => jumpEvent(-1));
$("next-event").addEventListener("click", () => jumpEvent(1));
$("layer-kind").addEventListener("change", (e) => {
  view.kind = e.target.value;
  $("layer-uav").disabled = view.kind === "coverage";
  drawLegend();
  ask();
});
$("layer-uav").addEventListener("change", (e) => {
  view.uav = Number(e.target.value);
  drawLegend();
  ask();
});
$("show-truth").addEventListener("change", () => render(view.current));
$("timeline").addEventListener("click", (e) => {
  const button = e.target.closest("button");
  if (button) jumpToStep(Number(button.dataset.step));
});
connect();
