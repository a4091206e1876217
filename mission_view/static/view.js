// The mission view page: one WebSocket (/ws) brings the mission's layout, its steps and the
// heat layer asked for; the map is Leaflet (vendored, no tiles) in the mission frame, 1 unit =
// 1 m, x east, y north from the area's south-west corner. Works the same live and in a replay.
"use strict";

const TRAIL_STEPS = 30;
const PALETTE = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2",
  "#17becf", "#bcbd22", "#393b79", "#637939", "#ad494a", "#7b4173", "#3182bd", "#e6550d",
  "#31a354", "#756bb1", "#636363", "#843c39", "#5254a3"];
const EVENT_ICONS = { engagement: "engaged", miss: "miss", override: "override",
  refusal: "refused", warning: "warning", link: "link", phase: "" };

const view = {
  layout: null, steps: [], events: [], current: -1, follow: true, ended: false,
  kind: "coverage", uav: 0, layerStep: null, layerKind: null, layerUav: null, layerCount: 0,
  map: null, ws: null, vehicles: [], heatCanvas: null,
  renderedSteps: [],  // every step shown while following the mission live
};
window.missionView = view;  // read by the browser tests

const $ = (id) => document.getElementById(id);
const pt = (x, y) => L.latLng(y * 1000, x * 1000);
const colour = (i) => PALETTE[i % PALETTE.length];

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

function initMap(layout) {
  const [w, h] = layout.area_km;
  const map = L.map("map", { crs: L.CRS.Simple, minZoom: -14, maxZoom: 3, zoomSnap: 0.25,
    attributionControl: false });
  const bounds = L.latLngBounds(pt(0, 0), pt(w, h));
  map.fitBounds(bounds.pad(0.04));
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

  L.rectangle(bounds, { fill: false, color: "#333", weight: 1, interactive: false }).addTo(map);
  for (const line of layout.graticule) {
    const pts = line.points.map(([x, y]) => pt(x, y));
    L.polyline(pts, { color: "#999", weight: 0.7, dashArray: "3 4", interactive: false }).addTo(map);
    const anchor = line.axis === "lat" ? pts[0] : pts[0];
    L.marker(anchor, { interactive: false, icon: L.divIcon({ className: "grid-label",
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
  for (let i = 0; i < layout.uav_count; i++) {
    const trail = L.polyline([], { color: colour(i), weight: 2, opacity: 0.8, interactive: false })
      .addTo(map);
    const leg = L.polyline([], { color: colour(i), weight: 1, dashArray: "4 4", opacity: 0.9,
      interactive: false }).addTo(map);
    const target = L.circleMarker(pt(0, 0), { radius: 3, color: colour(i), weight: 1.5,
      fill: false }).bindTooltip(`UAV ${i + 1}: guided target`).addTo(map);
    const icon = L.divIcon({ className: "uav-icon", iconSize: [16, 16], iconAnchor: [8, 8],
      html: `<svg width="16" height="16" viewBox="-8 -8 16 16"><path d="M7,0 L-6,-5 L-3,0 L-6,5 Z"
        fill="${colour(i)}" stroke="white" stroke-width="1"/></svg><span>${i + 1}</span>` });
    const marker = L.marker(pt(0, 0), { icon, keyboard: false }).addTo(map);
    marker.getElement().dataset.uav = String(i);
    marker.bindTooltip(`UAV ${i + 1}`);
    view.vehicles.push({ trail, leg, target, marker });
  }
  if (!layout.truth) {
    $("show-truth").parentElement.style.display = "none";
    $("truth-legend").style.display = "none";
  }
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
  const L_ = view.layout;
  s.vehicles.forEach((v, i) => {
    const g = view.vehicles[i];
    if (!g) return;
    g.marker.setLatLng(pt(v.x_km, v.y_km));
    const el = g.marker.getElement();
    el.querySelector("svg").style.transform = `rotate(${-v.heading_deg}deg)`;
    el.classList.toggle("lost", !v.active);
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
  });
  drawEngaged(k);
  drawTruth(s);
  $("stepinfo").textContent = `step ${s.step} / ${L_.steps}`;
  const late = $("lateness");
  late.textContent = L_.source === "mavlink" ? `late steps ${s.late_steps}${s.late ? " (this one late)" : ""}` : "";
  late.classList.toggle("late", s.late);
  $("totals").textContent = `coverage ${(100 * s.coverage).toFixed(1)} %, engaged ${s.engaged}` +
    ` (value ${fmt(s.engaged_value, 0)})`;
  const rows = s.vehicles.map((v, i) => {
    const lost = !v.active && !v.done;
    const link = v.last_heard_s === null ? "–" : lost ? `LOST ${fmt(v.last_heard_s, 1)} s` :
      `${fmt(v.last_heard_s, 1)} s`;
    const signed = v.signed === null ? "–" : v.signed ? "yes" : "no";
    return `<tr data-uav="${i}"><td><span class="swatch" style="background:${colour(i)}"></span>${i + 1}</td>` +
      `<td>${v.mode || "–"}</td><td>${v.planner_mode || "–"}</td>` +
      `<td>${fmt(v.ground_speed_mps)} / ${fmt(v.airspeed_mps)}</td>` +
      `<td class="${lost ? "lost" : ""}">${link}</td><td>${signed}</td></tr>`;
  });
  $("vehicles").tBodies[0].innerHTML = rows.join("");
  drawTimeline(k);
  const slider = $("slider");
  slider.max = String(view.steps.length - 1);
  slider.value = String(k);
  $("slider-label").textContent = `step ${s.step}` +
    (L_.step_s ? ` (${Math.round(s.step * L_.step_s)} s simulated)` : "");
}

function drawEngaged(k) {
  const layer = view.engagedLayer;
  layer.clearLayers();
  for (const e of view.events) {
    if (e.step > view.steps[k].step) break;
    if (e.kind !== "engagement" || e.x_km === null) continue;
    const id = (e.text.match(/target (\d+)/) || [])[1] || "";
    L.marker(pt(e.x_km, e.y_km), { icon: L.divIcon({ className: "engaged-icon", iconSize: [18, 18],
      iconAnchor: [9, 9], html: `<span class="star">&#9733;</span><span class="engaged-label">${id}</span>` }) })
      .bindTooltip(`step ${e.step}, UAV ${e.uav + 1}: ${e.text}`).addTo(layer);
  }
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

function drawTimeline(k) {
  const step = view.steps[k].step;
  const shown = view.events.filter((e) => e.step <= step).slice(-300).reverse();
  $("timeline").innerHTML = shown.map((e) =>
    `<li class="${e.kind}" data-step="${e.step}" value="${e.step}">` +
    `${e.uav === null ? "" : `UAV ${e.uav + 1}: `}${escapeHtml(e.text)}</li>`).join("");
}

function escapeHtml(text) {
  return String(text).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" })[c]);
}

// ------------------------------------------------------------------ talking to the server

function ask() {
  if (!view.ws || view.ws.readyState !== WebSocket.OPEN) return;
  const step = view.follow ? null : (view.steps[view.current] || {}).step ?? null;
  view.ws.send(JSON.stringify({ type: "view", kind: view.kind, uav: view.uav, step }));
}

function setFollow(on) {
  view.follow = on && view.layout && view.layout.live && !view.ended;
  $("follow").classList.toggle("active", view.follow);
}

function onMessage(ev) {
  const msg = JSON.parse(ev.data);
  if (msg.type === "mission") {
    const first = !view.layout;
    view.layout = msg;
    if (first) {
      initMap(msg);
      const sel = $("layer-uav");
      sel.innerHTML = Array.from({ length: msg.uav_count }, (_, i) =>
        `<option value="${i}">UAV ${i + 1}</option>`).join("");
      $("title").textContent = `${msg.scenario}, seed ${msg.seed}, ` +
        (msg.live ? `live (${msg.source === "mavlink" ? "over MAVLink" : msg.source})` : `replay of ${msg.source === "mavlink" ? "a MAVLink mission" : "an offline run"}`);
      $("follow").style.display = msg.live ? "" : "none";
      setFollow(msg.live);
      drawLegend();
    }
  } else if (msg.type === "steps") {
    for (const s of msg.steps) {
      view.steps.push(s);
      for (const e of s.events) view.events.push(e);
    }
    if (view.follow || view.current < 0) render(view.layout.live ? view.steps.length - 1 : view.steps.length - 1);
    else $("slider").max = String(view.steps.length - 1);
  } else if (msg.type === "layer") {
    drawHeat(msg);
  } else if (msg.type === "phase") {
    $("phase").textContent = msg.text;
  } else if (msg.type === "end") {
    view.ended = true;
    setFollow(false);
    if (view.layout.live) $("phase").textContent = "mission over";
  }
}

function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  view.ws = ws;
  ws.onopen = () => { $("connection").textContent = "connected"; $("connection").className = "on"; ask(); };
  ws.onmessage = onMessage;
  ws.onclose = () => {
    $("connection").textContent = view.ended ? "mission over, disconnected" : "disconnected";
    $("connection").className = "off";
  };
}

$("slider").addEventListener("input", (e) => {
  setFollow(false);
  render(Number(e.target.value));
  ask();
});
$("follow").addEventListener("click", () => {
  setFollow(true);
  render(view.steps.length - 1);
  ask();
});
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
  const li = e.target.closest("li");
  if (!li) return;
  const step = Number(li.dataset.step);
  const k = view.steps.findIndex((s) => s.step === step);
  if (k >= 0) { setFollow(false); render(k); ask(); }
});
connect();
