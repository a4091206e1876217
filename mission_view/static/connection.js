// The mission view's connection to its server: the WebSocket (/ws) and its messages (mission,
// steps, phase, layer, end), the page's requests (the layer and step to show), and losing the
// server: the banner, the stale link ages and the reconnection (1, 2, 4, up to 10 s).
"use strict";

const RECONNECT_MAX_S = 10;

// how long the page has had no word from the server (s), 0 while connected
function staleSeconds() {
  if (view.conn.state === "connected" || view.ended || !view.conn.lastMessageAt) return 0;
  return (performance.now() - view.conn.lastMessageAt) / 1000;
}

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

connect();
