// the 2D ultrasound view (view2d/page.html): draws the frame, the model's sections and the
// contours on a canvas, queues clicks and sends them one at a time (see view2d/__init__.py)
const TOKEN = document.body.dataset.token;
const OPENED = Date.now();  // when this page began, on the clock its beacon uses as it is left
const ACCESS = document.body.dataset.access;  // the viewer's token, when it asks for one
const POLL = Number(document.body.dataset.poll);
const IN_PROGRESS = document.body.dataset.drawing;
const RULER = 34, TOP = 22;
let zoom = 2, userZoom = false, state = null, etag = "", img = null, imgId = null;
let pending = [], sending = false;
window.navappLatencies = [];
const cv = document.getElementById("cv"), g = cv.getContext("2d");
const $ = id => document.getElementById(id);
function url(p){
  return p + (p.includes("?") ? "&" : "?") + "c=" + encodeURIComponent(TOKEN) + (ACCESS ? "&t=" + encodeURIComponent(ACCESS) : "");
}
// a refusal or error answered to this page's own click or command stays until its next one: a
// state poll answered just after it (a plane change asked before the click) had wiped it at once
let refusal = "";
function msg(t){ $("msg").textContent = t || refusal; }
function refused(t){ refusal = t || ""; msg(refusal); }

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
    for (const f of (c.flags || [])){  // a worst point of the last fit: ring + residual
      const p = c.vertices[f.v]; if (!p) continue; const x = X(p[0]), y = Y(p[1]);
      g.strokeStyle = f.colour; g.lineWidth = 2; g.beginPath(); g.arc(x, y, 8, 0, 7); g.stroke();
      g.fillStyle = f.colour; g.font = "bold 12px sans-serif"; g.fillText(f.text, x + 10, y + 4); }
    if (c.centroid){ const x = X(c.centroid[0]), y = Y(c.centroid[1]);
      g.strokeStyle = "#fff"; g.lineWidth = 1; g.beginPath(); g.moveTo(x - 4, y); g.lineTo(x + 4, y);
      g.moveTo(x, y - 4); g.lineTo(x, y + 4); g.stroke(); }
  }
  const d = state.drawing ? state.drawing.vertices.slice() : [];
  const mine = pending.filter(p => p.plane === state.plane_index);  // a click aimed at another plane stays there
  const v = d.concat(mine.map(p => [p.col, p.row]));
  if (v.length) poly(v, false, IN_PROGRESS, 2, mine.length);
  g.restore();
}

function apply(s){
  state = s; etag = s.etag;
  if (!userZoom && s.width) zoom = window.innerWidth >= RULER + 2 * s.width + 8 ? 2 : 1;
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

// the server answers, but not for this page's view: it was restarted (its views are new), and
// the viewer's own page reconnects only after a while; a reload gets a view at once
const RESTARTED = "The navapp server was restarted. Reload the page: the session's data and result come back; " +
  "clicks made while it was down are not kept.";
function restarted(){ $("gone").textContent = RESTARTED; $("gone").style.display = "block"; }
async function poll(){
  try {
    // the tab's pixel ratio: viser reports the 3D canvas in device pixels, the layout is in CSS pixels
    const r = await fetch(url("/us/state?v=" + encodeURIComponent(etag) + "&dpr=" + window.devicePixelRatio));
    if (r.status === 404) restarted(); else $("gone").style.display = "none";
    if (r.status === 200) apply(await r.json());
  } catch (e) { $("gone").style.display = "block"; }
  setTimeout(poll, POLL);
}

async function post(path, body){
  const r = await fetch(url(path), {method: "POST", body: JSON.stringify(body)});
  const t = await r.text();
  if (!r.ok) return {error: t, status: r.status};
  return JSON.parse(t);
}

async function pump(){
  if (sending) return;
  sending = true;
  while (pending.length){
    const p = pending[0];
    try {
      const s = await post("/us/click", {col: p.col, row: p.row, plane: p.plane, feature: p.feature});
      if (s.status === 404) {
        restarted(); pending.length = 0; break;  // a view this server does not know: nothing to deliver to
      }
      $("gone").style.display = "none";
      window.navappLatencies.push(performance.now() - p.t);
      pending.shift();
      if (s.error) { refused(s.error); } else { msg(""); apply(s); }
    } catch (e) { $("gone").style.display = "block"; await new Promise(r => setTimeout(r, 500)); }
  }
  sending = false; draw();
}

cv.addEventListener("mousedown", e => {
  if (e.button !== 0) return;
  const p = toPixel(e); if (!p) return;
  refusal = "";
  // what the click was aimed at, fixed now: the plane may change (3D panel, guide) while it waits
  pending.push({col: p[0], row: p[1], plane: state.plane_index, feature: $("feat").value, t: performance.now()});
  draw(); pump();
});
async function command(cmd, extra){
  while (sending || pending.length) await new Promise(r => setTimeout(r, 20));  // after the clicks before it
  refusal = "";
  const s = await post("/us/command", Object.assign({cmd: cmd, feature: $("feat").value}, extra || {}));
  if (s.error) refused(s.error); else { msg(s.message || ""); apply(s); }
}
$("close").onclick = () => command("Close");
$("finish").onclick = () => command("Finish line");
$("undo").onclick = () => command("Undo");
$("feat").onchange = () => command("Feature");
$("plane").onchange = () => { if ($("plane").value !== "") command("Plane", {plane: parseInt($("plane").value)}); };
// a reload is the same tab: its page takes back the work of the page before (undo history,
// contour in progress, plane). sessionStorage is per tab, so it names that page exactly; a
// browser that refuses storage to this frame (another site than the viewer) names none, and
// the server takes the one tab that has just gone, if there is exactly one. A page being left
// says so at once (a beacon is sent as the page goes): the viewer's connection of a reloaded tab
// can close many seconds after its new page asked, on a loaded server. Both times are on this
// browser's clock, the server's order of hearing them being no guide under load
window.addEventListener("pagehide", () => {
  try { navigator.sendBeacon(url("/us/going"), JSON.stringify({at: Date.now()})); } catch (e) {}
});
async function resume(){
  let prev = null;
  try { prev = sessionStorage.getItem("navapp-view"); sessionStorage.setItem("navapp-view", TOKEN); } catch (e) {}
  if (prev === TOKEN) return;
  for (let i = 0; i < 240; i++){  // the old page's connection may close a while after this one opened
    try {
      const s = await post("/us/resume", {previous: prev || "", opened: OPENED});
      if (!s.error) { apply(s); return; }
      if (!s.error.startsWith("wait")) return;
    } catch (e) {}
    await new Promise(r => setTimeout(r, 500));
  }
}
$("z1").onclick = () => { zoom = 1; userZoom = true; draw(); };
$("z2").onclick = () => { zoom = 2; userZoom = true; draw(); };
// 2× where the frame is wide enough: the viewer docks it narrower on a narrow window, after the page loaded
function fitZoom(){
  if (userZoom || !state || !state.width) return;
  const z = window.innerWidth >= RULER + 2 * state.width + 8 ? 2 : 1;
  if (z !== zoom){ zoom = z; draw(); }
}
window.addEventListener("resize", fitZoom);
document.addEventListener("keydown", e => {
  if (e.key === "Enter") command("Close");
  if ((e.ctrlKey || e.metaKey) && e.key === "z") command("Undo");
});
poll();
resume();
