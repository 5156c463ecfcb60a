"""The 2D ultrasound view: a small HTTP server whose page draws the current B-mode frame at
native pixel scale on a canvas, with mm rulers, the model's sections and the drawn
contours, and sends clicks back as pixels.

viser's GUI has no click events on images, so the view is a page of its own, embedded in a
viser panel as an iframe (one per browser tab, identified by a token). Clicks are queued in
the page and sent one at a time; a vertex is drawn hollow until the server has stored it
and filled once acknowledged, so no click is lost however fast they come, and a failed
request is retried, not dropped. The page polls the state (an ETag per client) a few times
a second, so contours committed in another tab appear here too. No viser here: the app
passes a ``provider`` with ``view_etag``, ``view_state``, ``view_image``, ``view_click``
and ``view_command``.
"""

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import parse_qs, urlparse

POLL_MS = 250  # how often a page asks whether anything changed

PAGE = r"""<!doctype html>
<html><head><meta charset="utf-8"><title>navapp ultrasound</title>
<style>
 body{margin:0;font:13px system-ui,sans-serif;background:#1b1b1b;color:#ddd}
 #bar{display:flex;flex-wrap:wrap;gap:4px;align-items:center;padding:4px}
 button,select{font:inherit;padding:2px 6px}
 #title{padding:0 4px;font-weight:600}
 #msg{padding:2px 4px;min-height:1.2em;color:#ffb347}
 #gone{display:none;background:#a00;color:#fff;padding:4px}
 #legend span{display:inline-block;margin-right:8px}
 #legend i{display:inline-block;width:14px;height:3px;vertical-align:middle;margin-right:3px}
 #targets{padding:2px 4px}
 canvas{display:block;cursor:crosshair}
</style></head><body>
<div id="gone">The navapp server is not answering — is it still running?
 Nothing drawn so far is lost; clicks wait until it is back.</div>
<div id="bar">
 <select id="plane" title="the plane this tab shows and draws on"></select>
 <select id="feat"><option>PV contour</option><option>HV contour</option><option>Posterior surface</option></select>
 <button id="close" title="close the contour (Enter)">Close</button>
 <button id="finish" title="end an open line">Finish line</button>
 <button id="undo" title="undo your last action (Ctrl+Z)">Undo</button>
 <span>zoom</span><button id="z1">1×</button><button id="z2">2×</button>
</div>
<div id="title">No plane shown yet.</div>
<div id="msg"></div>
<canvas id="cv" width="10" height="10"></canvas>
<div id="legend"></div>
<div id="targets"></div>
<script>
const TOKEN = "__TOKEN__";
const POLL = __POLL__;
const RULER = 34, TOP = 22;
let zoom = 2, state = null, etag = "", img = null, imgId = null;
let pending = [], sending = false;
window.navappLatencies = [];
const cv = document.getElementById("cv"), g = cv.getContext("2d");
const $ = id => document.getElementById(id);
function url(p){ return p + (p.includes("?") ? "&" : "?") + "c=" + TOKEN; }
function msg(t){ $("msg").textContent = t || ""; }

function toPixel(e){
  const r = cv.getBoundingClientRect();
  const col = Math.floor((e.clientX - r.left - RULER) / zoom);
  const row = Math.floor((e.clientY - r.top - TOP) / zoom);
  if (!state || !state.plane || col < 0 || row < 0 || col >= state.width || row >= state.height) return null;
  return [col, row];
}
const X = c => RULER + (c + 0.5) * zoom, Y = r => TOP + (r + 0.5) * zoom;

function draw(){
  if (!state || !state.plane){ cv.width = 10; cv.height = 10; return; }
  const W = state.width, H = state.height, s = state.spacing;
  cv.width = RULER + W * zoom + 4; cv.height = TOP + H * zoom + 4;
  g.fillStyle = "#1b1b1b"; g.fillRect(0, 0, cv.width, cv.height);
  g.imageSmoothingEnabled = false;
  if (img && img.complete) g.drawImage(img, RULER, TOP, W * zoom, H * zoom);
  // rulers: depth (mm below the probe face) on the left, lateral on top
  g.strokeStyle = "#bbb"; g.fillStyle = "#bbb"; g.font = "10px sans-serif"; g.lineWidth = 1;
  for (let mm = 0; mm <= H * s + 1e-6; mm += 5){
    const y = TOP + mm / s * zoom, long = mm % 10 === 0;
    g.beginPath(); g.moveTo(RULER - (long ? 8 : 4), y); g.lineTo(RULER, y); g.stroke();
    if (long) g.fillText(mm + "", 2, y + 3);
  }
  const w2 = W * s / 2;
  for (let mm = -Math.floor(w2 / 5) * 5; mm <= w2; mm += 5){
    const x = RULER + (mm + w2) / s * zoom, long = mm % 10 === 0;
    g.beginPath(); g.moveTo(x, TOP - (long ? 8 : 4)); g.lineTo(x, TOP); g.stroke();
    if (long) g.fillText(mm + "", x - 6, 10);
  }
  g.fillText("mm", 2, 10);
  g.save(); g.beginPath(); g.rect(RULER, TOP, W * zoom, H * zoom); g.clip();
  for (const o of state.overlays){
    if (!o.visible) continue;
    g.strokeStyle = o.colour; g.lineWidth = o.dashed ? 1.5 : 2; g.setLineDash(o.dashed ? [5, 4] : []);
    g.beginPath();
    for (const q of o.segments){ g.moveTo(X(q[0]), Y(q[1])); g.lineTo(X(q[2]), Y(q[3])); }
    g.stroke();
  }
  g.setLineDash([]);
  const poly = (v, closed, colour, width, pend) => {
    g.strokeStyle = colour; g.lineWidth = width; g.beginPath();
    v.forEach((p, i) => i ? g.lineTo(X(p[0]), Y(p[1])) : g.moveTo(X(p[0]), Y(p[1])));
    if (closed && v.length > 2) g.closePath();
    g.stroke();
    v.forEach((p, i) => { g.beginPath(); g.arc(X(p[0]), Y(p[1]), 3, 0, 7);
      if (pend && i >= v.length - pend) { g.stroke(); } else { g.fillStyle = colour; g.fill(); } });
  };
  for (const c of state.contours){
    poly(c.vertices, c.closed, c.colour, 2, 0);
    if (c.centroid){ const x = X(c.centroid[0]), y = Y(c.centroid[1]);
      g.strokeStyle = "#fff"; g.lineWidth = 1; g.beginPath(); g.moveTo(x - 4, y); g.lineTo(x + 4, y);
      g.moveTo(x, y - 4); g.lineTo(x, y + 4); g.stroke(); }
  }
  const d = state.drawing ? state.drawing.vertices.slice() : [];
  const v = d.concat(pending);
  if (v.length) poly(v, false, "#ffe033", 2, pending.length);
  g.restore();
}

function apply(s){
  state = s; etag = s.etag;
  $("title").textContent = s.plane ? s.plane : "No plane shown yet: choose one in the Ultrasound panel.";
  if (s.feature && document.activeElement !== $("feat")) $("feat").value = s.feature;
  const sel = $("plane"), opts = (s.planes || []).map(p => p.index + ":" + p.label).join("|");
  if (sel.dataset.opts !== opts){
    sel.dataset.opts = opts;
    sel.innerHTML = `<option value="">choose a plane…</option>` +
      (s.planes || []).map(p => `<option value="${p.index}">${p.label}</option>`).join("");
  }
  const idx = s.plane_index === null || s.plane_index === undefined ? "" : String(s.plane_index);
  if (document.activeElement !== sel) sel.value = idx;
  if (s.plane && s.image_id !== imgId){
    imgId = s.image_id; const im = new Image(); im.onload = () => { img = im; draw(); };
    im.src = url("/us/image?id=" + encodeURIComponent(s.image_id));
  }
  $("legend").innerHTML = s.legend.map(o => `<span><i style="background:${o.colour}"></i>${o.name}</span>`).join("");
  $("targets").innerHTML = s.targets.map(t => `<div>${t}</div>`).join("");
  msg(s.message || "");
  draw();
}

async function poll(){
  try {
    const r = await fetch(url("/us/state?v=" + encodeURIComponent(etag)));
    $("gone").style.display = "none";
    if (r.status === 200) apply(await r.json());
  } catch (e) { $("gone").style.display = "block"; }
  setTimeout(poll, POLL);
}

async function post(path, body){
  const r = await fetch(url(path), {method: "POST", body: JSON.stringify(body)});
  const t = await r.text();
  if (!r.ok) return {error: t};
  return JSON.parse(t);
}

async function pump(){
  if (sending) return;
  sending = true;
  while (pending.length){
    const p = pending[0];
    try {
      const s = await post("/us/click", {col: p[0], row: p[1], feature: $("feat").value});
      $("gone").style.display = "none";
      window.navappLatencies.push(performance.now() - p[2]);
      pending.shift();
      if (s.error) { msg(s.error); } else { msg(""); apply(s); }
    } catch (e) { $("gone").style.display = "block"; await new Promise(r => setTimeout(r, 500)); }
  }
  sending = false; draw();
}

cv.addEventListener("mousedown", e => {
  if (e.button !== 0) return;
  const p = toPixel(e); if (!p) return;
  pending.push([p[0], p[1], performance.now()]); draw(); pump();
});
async function command(cmd, extra){
  while (sending || pending.length) await new Promise(r => setTimeout(r, 20));  // after the clicks before it
  const s = await post("/us/command", Object.assign({cmd: cmd, feature: $("feat").value}, extra || {}));
  if (s.error) msg(s.error); else { msg(s.message || ""); apply(s); }
}
$("close").onclick = () => command("Close");
$("finish").onclick = () => command("Finish line");
$("undo").onclick = () => command("Undo");
$("feat").onchange = () => command("Feature");
$("plane").onchange = () => { if ($("plane").value !== "") command("Plane", {plane: parseInt($("plane").value)}); };
$("z1").onclick = () => { zoom = 1; draw(); };
$("z2").onclick = () => { zoom = 2; draw(); };
document.addEventListener("keydown", e => {
  if (e.key === "Enter") command("Close");
  if ((e.ctrlKey || e.metaKey) && e.key === "z") command("Undo");
});
poll();
</script></body></html>
"""


class _Handler(BaseHTTPRequestHandler):
    provider = None  # set per server class

    def log_message(self, *args):  # the app's console is for the user, not for every poll
        pass

    def _send(self, code, body: bytes, ctype="application/json"):
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Cache-Control", "no-store")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def _query(self):
        u = urlparse(self.path)
        return u.path, {k: v[0] for k, v in parse_qs(u.query).items()}

    def do_GET(self):
        path, q = self._query()
        token = q.get("c", "")
        try:
            if path == "/us":
                page = PAGE.replace("__TOKEN__", token).replace("__POLL__", str(POLL_MS))
                return self._send(200, page.encode(), "text/html; charset=utf-8")
            if path == "/us/state":
                if q.get("v") and self.provider.view_etag(token) == q.get("v"):
                    return self._send(204, b"")
                out = self.provider.view_state(token)
                if out is None:
                    return self._send(404, b"unknown view")
                if out["etag"] == q.get("v"):
                    return self._send(204, b"")
                return self._send(200, json.dumps(out).encode())
            if path == "/us/image":
                png = self.provider.view_image(token)
                if png is None:
                    return self._send(404, b"no image")
                return self._send(200, png, "image/png")
        except Exception as exc:  # a failed request must not take the server down
            return self._send(500, f"{exc.__class__.__name__}: {exc}".encode(), "text/plain")
        return self._send(404, b"not found", "text/plain")

    def do_POST(self):
        path, q = self._query()
        token = q.get("c", "")
        try:
            n = int(self.headers.get("Content-Length") or 0)
            body = json.loads(self.rfile.read(n) or b"{}")
            if path == "/us/click":
                err = self.provider.view_click(token, int(body["col"]), int(body["row"]), str(body.get("feature", "")))
            elif path == "/us/command":
                plane = body.get("plane")
                err = self.provider.view_command(token, str(body["cmd"]), str(body.get("feature", "")),
                                                 None if plane is None else int(plane))
            else:
                return self._send(404, b"not found", "text/plain")
        except (ValueError, KeyError, TypeError) as exc:
            return self._send(400, f"bad request: {exc}".encode(), "text/plain")
        except Exception as exc:
            return self._send(500, f"{exc.__class__.__name__}: {exc}".encode(), "text/plain")
        if err:
            return self._send(409, err.encode(), "text/plain")
        return self._send(200, json.dumps(self.provider.view_state(token) or {}).encode())


class View2DServer:
    """Serves the 2D view pages on ``host:port`` (port 0: any free port) in a thread."""

    def __init__(self, provider, host="127.0.0.1", port=0):
        handler = type("Handler", (_Handler,), {"provider": provider})
        self.httpd = ThreadingHTTPServer((host, port), handler)
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self.host = host
        self._thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self._thread.start()

    def page_url(self, token: str, host: str | None = None) -> str:
        return f"http://{host or self.host}:{self.port}/us?c={token}"

    def stop(self):
        self.httpd.shutdown()
        self.httpd.server_close()
