// The mission view's timeline (view.js draws the step): the events known, newest first, with a
// filter by kind and jumps to an event's step (click, Enter, previous / next event).
"use strict";

const KIND_NAMES = { engagement: "engagements", miss: "misses", threat: "threats found", override: "envelope",
  refusal: "refused", warning: "warnings", link: "link", phase: "phase", operator: "operator" };

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

$("prev-event").addEventListener("click", () => jumpEvent(-1));
$("next-event").addEventListener("click", () => jumpEvent(1));
$("timeline").addEventListener("click", (e) => {
  const button = e.target.closest("button");
  if (button) jumpToStep(Number(button.dataset.step));
});
