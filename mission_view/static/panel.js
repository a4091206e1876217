// The mission view's vehicle panel (click a UAV on the map or in the table, or Enter on its
// row), the cursor's position readout and the distance measure. Uses view.js's globals.
// Selecting a UAV (or none) is announced as
//   window.dispatchEvent(new CustomEvent("swarm:select", {detail: {uav: <0-based id or null>}}))
// for actions.js, which fills #vehicle-actions and #operator-actions.
"use strict";

const MODE_REASONS = {
  heuristic: "searching: the ants' choice by pheromone and target probability (eq 36)",
  deterministic: "pulled by the potential field towards likely targets (eq 35)",
  engage: "engaging a target it believes is here",
  escape: "leaving a threat zone",
  return: "flying home: its range, or the mission's end",
  hold: "holding: home, or nothing to do",
};
const GPS_FIX = ["no GPS", "no fix", "2D fix", "3D fix", "DGPS", "RTK float", "RTK fixed",
  "static", "PPP"];

function selectVehicle(i) {
  view.selected = i;
  $("vehicle-panel").hidden = i === null;
  if (i === null) $("vp-follow").checked = false;
  window.dispatchEvent(new CustomEvent("swarm:select", { detail: { uav: i } }));
  if (view.current >= 0) render(view.current);
  if (i !== null) $("vehicle-panel").scrollIntoView({ block: "start" });
}

function latLonText(x, y) {
  const [lat, lon] = kmToGeo(x, y);
  return `${Math.abs(lat).toFixed(5)}°${lat >= 0 ? "N" : "S"} ${Math.abs(lon).toFixed(5)}°${lon >= 0 ? "E" : "W"}`;
}

// distance (km) and bearing (degrees from north, clockwise) from a to b in the mission frame
function rangeBearing([ax, ay], [bx, by]) {
  const dx = bx - ax, dy = by - ay;
  return [Math.hypot(dx, dy), (Math.atan2(dx, dy) * 180 / Math.PI + 360) % 360];
}

const na = (v, text) => (v === null || v === undefined ? "n/a" : text);

function vehicleFields(v, i) {
  const stale = view.current === view.steps.length - 1 ? staleSeconds() : 0;
  const state = v.done ? "home (done)" : v.active ? "flying" : "LOST";
  const why = MODE_REASONS[v.planner_mode] || "";
  const home = v.home_km ? rangeBearing([v.x_km, v.y_km], v.home_km) : null;
  const target = v.target_km && v.active && !v.done ? v.target_km : null;
  return [
    ["state", state],
    ["flight mode", v.mode || "n/a"],
    ["planner mode", v.planner_mode ? `${v.planner_mode}${why ? `: ${why}` : ""}` : "n/a"],
    ["position", `${latLonText(v.x_km, v.y_km)} (x ${v.x_km.toFixed(2)}, y ${v.y_km.toFixed(2)} km)`],
    ["altitude", na(v.alt_m, `${fmt(v.alt_m)} m above home`)],
    ["speed", `ground ${na(v.ground_speed_mps, `${fmt(v.ground_speed_mps, 1)} m/s`)}, ` +
      `air (commanded) ${na(v.airspeed_mps, `${fmt(v.airspeed_mps, 1)} m/s`)}`],
    ["course", `${((90 - v.heading_deg + 360) % 360).toFixed(0)}° from north`],
    ["battery", na(v.battery_pct, `${v.battery_pct} %`)],
    ["GPS", na(v.gps_fix, GPS_FIX[v.gps_fix] || `fix type ${v.gps_fix}`)],
    ["home", home ? `${home[0].toFixed(2)} km, bearing ${home[1].toFixed(0)}°` : "n/a"],
    ["link", v.last_heard_s === null ? "n/a" :
      `heard ${fmt(v.last_heard_s + stale, 1)} s ago${stale ? " (or longer: no word from the server)" : ""}`],
    ["signing", v.signed === null ? "n/a" : v.signed ? "signed (MAVLink 2)" : "not signed"],
    ["last look", v.last_look === null || v.last_look === undefined ? "n/a" :
      `#${v.last_look}, ${fmt(v.last_look_s + stale, 1)} s ago`],
    ["guided target", target ? `${latLonText(...target)} (x ${target[0].toFixed(2)}, y ${target[1].toFixed(2)} km)` : "none"],
  ];
}

window.drawVehiclePanel = function drawVehiclePanel() {
  const i = view.selected, s = view.steps[view.current];
  if (i === null || !s || !s.vehicles[i]) return;
  const v = s.vehicles[i];
  $("vp-name").textContent = `UAV ${i + 1} at step ${s.step}`;
  $("vehicle-panel").querySelector(".swatch").style.background = colour(i);
  $("vp-fields").innerHTML = vehicleFields(v, i).map(([k, text]) =>
    `<dt>${k}</dt><dd data-field="${k}">${escapeHtml(text)}</dd>`).join("");
  if ($("vp-follow").checked) view.map.panTo(pt(v.x_km, v.y_km), { animate: false });
};

$("vp-close").addEventListener("click", () => selectVehicle(null));
$("vp-centre").addEventListener("click", () => {
  const v = view.steps[view.current]?.vehicles[view.selected];
  if (v) view.map.panTo(pt(v.x_km, v.y_km));
});
$("vp-follow").addEventListener("change", () => window.drawVehiclePanel());
const rowOf = (e) => e.target.closest("tr[data-uav]");
$("vehicles").addEventListener("click", (e) => { const r = rowOf(e); if (r) selectVehicle(Number(r.dataset.uav)); });
$("vehicles").addEventListener("keydown", (e) => {
  const r = rowOf(e);
  if (r && (e.key === "Enter" || e.key === " ")) { e.preventDefault(); selectVehicle(Number(r.dataset.uav)); }
});
document.addEventListener("keydown", (e) => {
  if (e.key === "Escape" && view.measure) stopMeasure();
  else if (e.key === "Escape" && view.selected !== null) selectVehicle(null);
});

// ------------------------------------------------------------------ cursor and measure

function whenMapReady(fn) {
  if (view.map) fn(); else setTimeout(() => whenMapReady(fn), 100);
}

function stopMeasure() {
  view.measure = null;
  $("measure").setAttribute("aria-pressed", "false");
  $("measure").classList.remove("active");
  document.getElementById("map").classList.remove("measuring");
}

whenMapReady(() => {
  const map = view.map;
  view.measureLayer = L.layerGroup().addTo(map);
  map.on("mousemove", (e) => {
    const [x, y] = toKm(e.latlng);
    $("cursor").textContent = `${latLonText(x, y)} · x ${x.toFixed(2)} km, y ${y.toFixed(2)} km`;
  });
  map.on("mouseout", () => { $("cursor").textContent = ""; });
  map.on("click", (e) => {
    if (!view.measure) return;
    const p = toKm(e.latlng);
    if (view.measure.length >= 2) { view.measure = []; view.measureLayer.clearLayers(); }
    view.measure.push(p);
    L.circleMarker(pt(...p), { radius: 3, color: "#000", weight: 1.5, interactive: false })
      .addTo(view.measureLayer);
    if (view.measure.length === 2) {
      const [d, b] = rangeBearing(...view.measure);
      L.polyline(view.measure.map((q) => pt(...q)), { color: "#000", weight: 1.5,
        dashArray: "6 3", interactive: false }).addTo(view.measureLayer);
      $("measure-text").textContent = `${d.toFixed(2)} km, bearing ${b.toFixed(0)}°`;
    }
  });
});

$("measure").addEventListener("click", () => {
  if (view.measure) { stopMeasure(); return; }
  view.measure = [];
  view.measureLayer.clearLayers();
  $("measure-text").textContent = "click two points on the map";
  $("measure").setAttribute("aria-pressed", "true");
  $("measure").classList.add("active");
  document.getElementById("map").classList.add("measuring");
});
