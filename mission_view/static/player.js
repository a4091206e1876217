// The mission view's player (footer): step back and forward, play / pause at a speed, the
// slider, and "follow live" back to the newest step of a live mission.
"use strict";

function showStep(k) {
  k = Math.max(0, Math.min(view.steps.length - 1, k));
  const newest = k === view.steps.length - 1 && view.layout.live && !view.ended &&
    view.conn.state === "connected";
  setFollow(newest);
  render(k);
  ask();
}

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

$("slider").addEventListener("input", (e) => { stopPlaying(); setFollow(false); render(Number(e.target.value)); ask(); });
$("follow").addEventListener("click", () => { stopPlaying(); setFollow(true); render(view.steps.length - 1); ask(); });
$("step-back").addEventListener("click", () => { stopPlaying(); setFollow(false); showStep(view.current - 1); });
$("step-forward").addEventListener("click", () => { stopPlaying(); showStep(view.current + 1); });
$("play").addEventListener("click", play);
$("speed").addEventListener("change", () => { if (view.playing !== null) { stopPlaying(); play(); } });
