"""The station's own pages: the operator's (viser's 3D view beside the live camera view and its
tools), the wearer's (the standing prompt, spoken), and the refusal without a token. Served only
to holders of a token, which the pages' scripts then send as the API's bearer token: the
operator's page carries the operator's, the wearer's page only the wearer's (which reads the
prompt and nothing else)."""

from __future__ import annotations

import json


def refused_page() -> str:
    return ("<!doctype html><title>wvr station</title><h1>401: this station needs its token</h1>"
            "<p>Open the address the station printed when it started (it ends in <code>?token=...</code>).</p>")


_OPERATOR = r"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>wvr station</title>
<style>
 body { margin: 0; font: 14px sans-serif; background: #16181c; color: #ddd; display: flex; height: 100vh; }
 #view3d { flex: 1 1 55%; border: 0; height: 100vh; }
 #side { flex: 0 0 660px; display: flex; flex-direction: column; padding: 8px; gap: 6px; overflow-y: auto; }
 #camera { width: 640px; height: 480px; background: #000; cursor: crosshair; }
 button { font-size: 14px; padding: 4px 10px; }
 #stop { background: #c00; color: #fff; font-weight: bold; }
 #prompt { font-size: 18px; color: #ffd24a; min-height: 22px; }
 #log { font-family: monospace; font-size: 12px; white-space: pre-wrap; max-height: 140px; overflow-y: auto; }
</style></head>
<body>
<iframe id="view3d" title="3D view"></iframe>
<div id="side">
 <div><b>Camera view</b> <span id="status">connecting...</span></div>
 <canvas id="camera" width="640" height="480"></canvas>
 <div id="prompt"></div>
 <div>Click on the camera view:
  <label><input type="radio" name="tool" value="fixate" checked> fixate</label>
  <label><input type="radio" name="tool" value="label"> label</label>
  <label><input type="radio" name="tool" value="box"> box</label>
  <label><input type="radio" name="tool" value="arrow"> arrow</label>
  <input id="text" value="here" size="14" title="label text">
 </div>
 <div>Mode:
  <button data-mode="hold">hold</button> <button data-mode="stabilise">stabilise (Path A)</button>
  <button data-mode="body">body (Path B)</button> <button data-mode="track">track</button>
  <button data-mode="explore" title="map: fixate where score = pose information + novelty is highest">explore (map)</button>
 </div>
 <div id="explore"></div>
 <div><button id="stop">EMERGENCY STOP</button> <button id="reset">reset</button>
  <a id="wearer" target="_blank" style="color:#8cf">wearer's page</a></div>
 <div id="log"></div>
</div>
<script id="camera-worker" type="text/x-worker">
// The camera view as pushed by /api/stream: "WVRF", seq, t_ms, length (u32 big-endian), JPEG.
let frames = 0;
onmessage = (e) => pull(e.data.origin, e.data.token, e.data.canvas);
async function pull(origin, token, canvas) {
  const ctx = canvas ? canvas.getContext("2d") : null;
  for (;;) {
    try {
      const r = await fetch(origin + "/api/stream", {headers: {"Authorization": "Bearer " + token}, cache: "no-store"});
      const reader = r.body.getReader();
      let buf = new Uint8Array(0);
      for (;;) {
        const {done, value} = await reader.read();
        if (done) break;
        const b = new Uint8Array(buf.length + value.length); b.set(buf); b.set(value, buf.length); buf = b;
        let frame = null;
        while (buf.length >= 16) {
          const dv = new DataView(buf.buffer, buf.byteOffset);
          const n = dv.getUint32(12);
          if (buf.length < 16 + n) break;
          frame = {seq: dv.getUint32(4), jpg: buf.slice(16, 16 + n)};
          buf = buf.slice(16 + n);
        }
        if (!frame) continue;                // only the newest of what arrived is drawn
        const bmp = await createImageBitmap(new Blob([frame.jpg], {type: "image/jpeg"}));
        const m = {seq: frame.seq, frames: ++frames, size: [bmp.width, bmp.height],
                   at: performance.timeOrigin + performance.now()};
        if (ctx) {
          if (canvas.width !== bmp.width) { canvas.width = bmp.width; canvas.height = bmp.height; }
          ctx.drawImage(bmp, 0, 0); bmp.close();
          postMessage(m);
        } else {
          m.bitmap = bmp; postMessage(m, [bmp]);
        }
      }
    } catch (e) {}
    await new Promise(res => setTimeout(res, 500));
  }
}
</script>
<script>
const TOKEN = __TOKEN__;
const H = {"Authorization": "Bearer " + TOKEN};
// The address to hand the wearer: their own token, which reads the prompt and nothing more.
document.getElementById("wearer").href = "/wearer?token=" + encodeURIComponent(__WEARER_TOKEN__);
// "#camera" opens the camera view alone (a slow machine, a measurement of the camera view).
if (location.hash === "#camera") document.getElementById("view3d").remove();
else document.getElementById("view3d").src = "/viser/";
const canvas = document.getElementById("camera");
const log = (m) => { const el = document.getElementById("log"); el.textContent = m + "\n" + el.textContent.slice(0, 4000); };
window.station = {frames: 0, seq: -1, times: [], last: null, clicks: [], size: [canvas.width, canvas.height]};
async function post(kind, body, source) {
  const r = await fetch("/api/" + kind, {method: "POST", headers: {...H, "Content-Type": "application/json",
                                                                   "X-Wvr-Source": source || "page"},
                                         body: JSON.stringify(body || {})});
  const j = await r.json();
  window.station.last = {status: r.status, ...j};
  log(kind + " " + JSON.stringify(body || {}) + " -> " + r.status + " " + (j.accepted ? "accepted" : j.reason));
  return j;
}
// The camera view is fetched, decoded and drawn in a worker, on an OffscreenCanvas where the
// browser has one: the 3D view's rendering holds the page's own thread (a software-rendered
// WebGL frame can take half a second) and must not hold the camera view back with it.
const worker = new Worker(URL.createObjectURL(new Blob([document.getElementById("camera-worker").textContent],
                                                        {type: "text/javascript"})));
const offscreen = canvas.transferControlToOffscreen ? canvas.transferControlToOffscreen() : null;
const ctx = offscreen ? null : canvas.getContext("2d");
worker.onmessage = (e) => {
  const S = window.station, m = e.data;
  if (m.bitmap) {                          // no OffscreenCanvas: the worker decoded, the page draws
    if (canvas.width !== m.bitmap.width) { canvas.width = m.bitmap.width; canvas.height = m.bitmap.height; }
    ctx.drawImage(m.bitmap, 0, 0); m.bitmap.close();
  }
  S.seq = m.seq; S.frames = m.frames; S.size = m.size; S.times.push(m.at - performance.timeOrigin);
  if (S.times.length > 200) S.times.shift();
};
worker.postMessage({origin: location.origin, token: TOKEN, canvas: offscreen}, offscreen ? [offscreen] : []);
async function poll() {
  for (;;) {
    try {
      const s = await (await fetch("/api/state", {headers: H, cache: "no-store"})).json();
      const ts = window.station.times, n = ts.length;
      const fps = n > 1 ? (1000 * (n - 1) / (ts[n - 1] - ts[0])).toFixed(1) : "-";
      document.getElementById("status").textContent =
        `t ${s.t === null ? "-" : s.t.toFixed(2)} s | ${s.mode} | ${s.features.length} features | loop ${s.loop_hz} Hz | view ${fps} fps` +
        (s.estop ? " | E-STOP LATCHED" : "") + (s.running ? "" : " | ENDED");
      document.getElementById("prompt").textContent = s.prompt ? "Wearer: " + s.prompt : "";
      const ex = s.explore, best = ex && ex.chosen !== null ? ex.candidates[ex.chosen] : null;
      document.getElementById("explore").textContent = !ex ? "" :
        `Explore: ${ex.objective} | ${ex.candidates.length} candidates` + (best ? ` | chosen ${best.score.toFixed(2)} ` +
        `(pose ${best.pose_info.toFixed(2)} + novelty ${best.novelty.toFixed(2)}, ${best.visible} features in view)` : "");
    } catch (e) {}
    await new Promise(res => setTimeout(res, 300));
  }
}
canvas.addEventListener("click", (e) => {
  const r = canvas.getBoundingClientRect();
  const [w, h] = window.station.size;       // the image's pixels (the canvas itself may be the worker's)
  const uv = [(e.clientX - r.left) * w / r.width, (e.clientY - r.top) * h / r.height];
  const tool = document.querySelector("input[name=tool]:checked").value;
  window.station.clicks.push({tool, uv, at: performance.now()});
  if (tool === "fixate") post("fixate", {uv}, "camera-view");
  else if (tool === "label") post("label", {uv, text: document.getElementById("text").value}, "camera-view");
  else post("object", {uv, kind: tool}, "camera-view");
});
document.querySelectorAll("button[data-mode]").forEach(b => b.onclick = () => post("mode", {mode: b.dataset.mode}));
document.getElementById("stop").onclick = () => post("stop", {reason: "operator's page"});
document.getElementById("reset").onclick = () => post("reset", {});
poll();
</script></body></html>
"""


_WEARER = r"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>wvr: for the wearer</title>
<style> body { font: 32px sans-serif; background: #000; color: #fff; text-align: center; padding-top: 20vh; }
 #prompt { color: #ffd24a; font-size: 48px; min-height: 60px; } button { font-size: 24px; } </style></head>
<body><div id="prompt">(nothing to do)</div><div id="mode"></div>
<p><button id="voice">speak the prompts</button></p>
<script>
const TOKEN = __TOKEN__;
let speak = false, said = "";
document.getElementById("voice").onclick = () => { speak = true; document.getElementById("voice").textContent = "speaking"; };
window.wearer = {prompts: []};
async function poll() {
  for (;;) {
    try {
      const s = await (await fetch("/api/prompt", {headers: {"Authorization": "Bearer " + TOKEN}, cache: "no-store"})).json();
      document.getElementById("prompt").textContent = s.prompt ? "Please " + s.prompt : "(nothing to do)";
      document.getElementById("mode").textContent = s.estop ? "camera stopped" : s.mode;
      if (s.prompt && s.prompt !== said) {
        said = s.prompt; window.wearer.prompts.push(s.prompt);
        if (speak && window.speechSynthesis) speechSynthesis.speak(new SpeechSynthesisUtterance("Please " + s.prompt));
      } else if (!s.prompt) { said = ""; }
    } catch (e) {}
    await new Promise(res => setTimeout(res, 500));
  }
}
poll();
</script></body></html>
"""


def operator_page(token: str, wearer_token: str) -> str:
    """The operator's page with the operator's token, and the wearer's page's address."""
    return _OPERATOR.replace("__WEARER_TOKEN__", json.dumps(wearer_token)).replace("__TOKEN__", json.dumps(token))


def wearer_page(wearer_token: str) -> str:
    """The wearer's page: it holds the wearer's token only (GET /api/prompt)."""
    return _WEARER.replace("__TOKEN__", json.dumps(wearer_token))
