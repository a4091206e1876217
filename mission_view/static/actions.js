// Operator actions on the mission view (docs/view.md, "Operator actions"): RTL one UAV, RTL all,
// hold and resume the search, end the mission, mark a sighting. Each is confirmed in a dialog and
// sent as POST /api/action {token, action, uav?, cell?}; the token comes from the page's URL
// (?token=..., printed by the daemon / demo). Without it, or refused, the page stays read-only
// and says why in one line. Touches only #operator-actions, #vehicle-actions (made here when the
// page has none) and its own dialog; the UAV acted on comes from the page's 'swarm:select' event.
"use strict";

(() => {
  const token = new URLSearchParams(location.search).get("token");
  const state = { enabled: false, reason: "", selected: null, uavCount: 0, grid: [0, 0],
    cellKm: 1, held: false, busy: false, last: null, answers: [] };
  window.operatorActions = state;  // read by the browser tests

  function el(tag, attrs = {}, text = "") {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
    if (text) e.textContent = text;
    return e;
  }

  // ---------------------------------------------------------------- containers and buttons

  let panel = document.getElementById("operator-actions");
  if (!panel) {
    panel = el("div", { id: "operator-actions" });
    (document.querySelector("header") || document.body).appendChild(panel);
  }
  let vehiclePanel = document.getElementById("vehicle-actions");
  const ownVehiclePanel = !vehiclePanel;  // no vehicle panel on the page: a UAV menu of our own
  if (!vehiclePanel) vehiclePanel = el("span", { id: "vehicle-actions" });

  const buttons = {
    hold: el("button", { type: "button", "data-action": "hold" }, "Hold search"),
    rtl_all: el("button", { type: "button", "data-action": "rtl_all" }, "RTL all"),
    end: el("button", { type: "button", "data-action": "end" }, "End mission"),
    mark: el("button", { type: "button", "data-action": "mark" }, "Mark sighting"),
  };
  const rtlOne = el("button", { type: "button", "data-action": "rtl" }, "RTL UAV");
  const uavMenu = el("select", { id: "operator-uav", "aria-label": "UAV to send home" });
  const status = el("span", { id: "operator-status", role: "status" });
  for (const b of Object.values(buttons)) panel.appendChild(b);
  if (ownVehiclePanel) {
    panel.appendChild(vehiclePanel);
    vehiclePanel.appendChild(uavMenu);
  }
  vehiclePanel.appendChild(rtlOne);
  panel.appendChild(status);

  function refresh() {
    const off = !state.enabled || state.busy;
    for (const b of [...Object.values(buttons), rtlOne]) {
      b.disabled = off;
      b.title = state.enabled ? "" : state.reason;
    }
    uavMenu.disabled = off;
    buttons.hold.textContent = state.held ? "Resume search" : "Hold search";
    buttons.hold.dataset.action = state.held ? "resume" : "hold";
    const uav = selectedUav();
    rtlOne.textContent = uav === null ? "RTL UAV" : `RTL UAV ${uav + 1}`;
    if (uav === null && !ownVehiclePanel) rtlOne.disabled = true;
    if (!state.enabled) status.textContent = state.reason;
  }

  function selectedUav() {
    if (ownVehiclePanel) return uavMenu.value === "" ? null : Number(uavMenu.value);
    return state.selected;
  }

  window.addEventListener("swarm:select", (e) => {
    const uav = e.detail ? e.detail.uav : null;
    state.selected = Number.isInteger(uav) ? uav : null;
    if (ownVehiclePanel && state.selected !== null) uavMenu.value = String(state.selected);
    refresh();
  });

  // ---------------------------------------------------------------- the confirmation dialog

  const dialog = el("dialog", { id: "operator-confirm", "aria-labelledby": "operator-question" });
  dialog.innerHTML = `<form method="dialog">
    <p id="operator-question"></p>
    <fieldset id="operator-where" hidden><legend>where (a grid cell, or lat/lon)</legend>
      <label>cell x <input id="operator-cell-x" type="number" min="0" step="1" size="4"></label>
      <label>cell y <input id="operator-cell-y" type="number" min="0" step="1" size="4"></label>
      <label>or lat <input id="operator-lat" type="number" step="any" size="9"></label>
      <label>lon <input id="operator-lon" type="number" step="any" size="9"></label>
      <button type="button" id="operator-pick">pick on the map</button>
    </fieldset>
    <p id="operator-problem" role="alert"></p>
    <button value="cancel" id="operator-cancel">Cancel</button>
    <button value="confirm" id="operator-ok">Confirm</button>
  </form>`;
  document.body.appendChild(dialog);
  const $ = (id) => document.getElementById(id);
  let pending = null;  // the action the dialog asks about

  const QUESTIONS = {
    rtl: (r) => `Send UAV ${r.uav + 1} home (RTL)? It leaves the mission for good.`,
    rtl_all: () => "Send every UAV home (RTL)? The mission ends when all are on their way.",
    hold: () => "Hold the search? Every plane circles its current target; no new targets " +
      "until you resume. The mission clock goes on.",
    resume: () => "Resume the search from where the planes are?",
    end: () => "End the mission now? The planes fly home and the result is written, as at " +
      "the mission's last step.",
    mark: () => "Mark a sighting: every UAV takes it in as a detection in that cell.",
  };

  function ask(action) {
    const request = { action };
    if (action === "rtl") {
      const uav = selectedUav();
      if (uav === null) return;
      request.uav = uav;
    }
    pending = request;
    $("operator-question").textContent = QUESTIONS[action](request);
    $("operator-where").hidden = action !== "mark";
    $("operator-problem").textContent = "";
    $("operator-pick").hidden = !(window.missionView && window.missionView.map);
    if (!dialog.open) dialog.showModal();
  }

  function where() {
    const num = (id) => $(id).value === "" ? null : Number($(id).value);
    const [x, y, lat, lon] = ["operator-cell-x", "operator-cell-y", "operator-lat",
      "operator-lon"].map(num);
    if (x !== null && y !== null) return { cell: [Math.floor(x), Math.floor(y)] };
    if (lat !== null && lon !== null) return { lat, lon };
    return null;
  }

  dialog.addEventListener("close", () => {
    if (dialog.returnValue !== "confirm" || !pending) { pending = null; return; }
    const request = pending;
    pending = null;
    if (request.action === "mark") {
      const at = where();
      if (!at) { pending = request; $("operator-problem").textContent =
        "give a cell (x and y) or lat and lon"; dialog.showModal(); return; }
      Object.assign(request, at);
    }
    send(request);
  });

  $("operator-pick").addEventListener("click", () => {
    const map = window.missionView && window.missionView.map;
    if (!map) return;
    dialog.close("pick");
    status.textContent = "click the map where the sighting is";
    map.once("click", (e) => {  // the page's own conversion (view.js; tiles: Web Mercator)
      const km = typeof window.toKm === "function" ? window.toKm(e.latlng) :
        [e.latlng.lng / 1000, e.latlng.lat / 1000];
      $("operator-cell-x").value = String(Math.floor(km[0] / state.cellKm));
      $("operator-cell-y").value = String(Math.floor(km[1] / state.cellKm));
      status.textContent = "";
      ask("mark");
    });
  });

  // ---------------------------------------------------------------- talking to the server

  async function post(body) {
    const res = await fetch("/api/action", { method: "POST",
      headers: { "Content-Type": "application/json" }, body: JSON.stringify({ ...body, token }) });
    let answer = {};
    try { answer = await res.json(); } catch (_) { /* an empty body */ }
    return { status: res.status, answer };
  }

  async function send(request) {
    state.busy = true;
    refresh();
    status.textContent = `${request.action}: sent…`;
    try {
      const { status: code, answer } = await post(request);
      const text = answer.result || answer.error || `HTTP ${code}`;
      state.last = { code, request, answer };
      state.answers.push(state.last);
      if (code === 200 && request.action === "hold") state.held = true;
      if (code === 200 && request.action === "resume") state.held = false;
      status.textContent = code === 200 ? `step ${answer.step}: ${text}` : text;
      if (code === 403) disable("token refused: read-only (open the URL the daemon printed)");
      if (code === 409) disable("the mission is over: no more actions");
    } catch (err) {
      status.textContent = `not sent: ${err}`;
    } finally {
      state.busy = false;
      refresh();
    }
  }

  function disable(reason) {
    state.enabled = false;
    state.reason = reason;
    refresh();
  }

  for (const b of [...Object.values(buttons), rtlOne]) {
    b.addEventListener("click", () => ask(b.dataset.action));
  }

  async function start() {
    if (!token) {
      disable("read-only: open the URL with ?token=... that the daemon printed to act");
      hideInReplay(40);
      return;
    }
    const { status: code, answer } = await post({ action: "check" }).catch(() => ({ status: 0 }));
    if (code === 404) { panel.hidden = true; disable("a replay takes no actions"); return; }
    if (code === 403) { disable("token refused: read-only (open the URL the daemon printed)"); return; }
    if (code !== 200) { disable("no answer from the server: read-only"); return; }
    if (!answer.open) { disable(`no more actions: ${answer.reason}`); return; }
    state.uavCount = answer.uav_count;
    state.grid = answer.grid;
    state.cellKm = answer.cell_km;
    uavMenu.innerHTML = '<option value="">UAV…</option>' + Array.from({ length: answer.uav_count },
      (_, i) => `<option value="${i}">UAV ${i + 1}</option>`).join("");
    state.enabled = true;
    state.reason = "";
    status.textContent = "actions on";
    refresh();
  }

  function hideInReplay(tries) {  // a replay has no actions at all: no buttons either
    const layout = window.missionView && window.missionView.layout;
    if (layout) { panel.hidden = layout.live === false; return; }
    if (tries > 0) setTimeout(() => hideInReplay(tries - 1), 250);
  }

  uavMenu.addEventListener("change", refresh);
  refresh();
  start();
})();
