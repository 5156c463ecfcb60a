"""What an idle tab does, and who asks for it (issue 50, item 7). A probe, not a test.

    python notes/scripts/tab_idle_probe.py navapp|bare [QUERY]

``navapp``: ``navapp serve --edge 12 --k 12`` on the demo (cache: $NAVAPP_CACHE or a temporary one).
``bare``: a viser server of the installed version with one 20,480-triangle sphere, lit as navapp lights
its scene (no shadows, no environment map); ``empty``: the same without the sphere.
QUERY (e.g. ``fixedDpr=0.5``) is appended to the viewer's address; HIDE="Targets,..." unticks those
of navapp's layers first; SHOT=file.png saves a screenshot.
Opens one 1366 x 768 tab in headless Chromium, waits until it idles, then over 10 s counts the
frames drawn (WebGL clears), draw calls and triangles, the websocket frames received, and lists
every setInterval the page registered (its period and the first lines of its caller's stack).
"""
import os
import subprocess
import sys
import tempfile
import time

import psutil
from playwright.sync_api import sync_playwright

WHAT = sys.argv[1] if len(sys.argv) > 1 else "navapp"
QUERY = sys.argv[2] if len(sys.argv) > 2 else ""
PORT = 8937
BARE = """
import time, trimesh, viser
s = viser.ViserServer(port={port})
s.scene.configure_default_lights(enabled=True, cast_shadow=False)  # as navapp's server
s.scene.configure_environment_map(hdri=None)
m = trimesh.creation.icosphere(subdivisions=5)  # 20,480 faces
s.scene.add_mesh_simple("/sphere", m.vertices, m.faces, color=(200, 120, 120))
print("viewer at http://127.0.0.1:{port}", flush=True)
while True:
    time.sleep(3600)
"""
INIT = """
window.__n = {frames: 0, clears: 0, draws: 0, tris: 0, ws: 0}; window.__t = []; window.__last = -1e9; window.__snap = -1; window.__calls = [];
window.__intervals = [];
const si = window.setInterval.bind(window);
window.setInterval = (f, ms, ...a) => {
  window.__intervals.push([ms, (new Error().stack || '').split('\\n').slice(2, 4).join(' | ')]);
  return si(f, ms, ...a);
};
const WS = window.WebSocket;
window.WebSocket = function(...a) {
  const w = new WS(...a);
  w.addEventListener('message', () => { window.__n.ws++; });
  return w;
};
window.WebSocket.prototype = WS.prototype;
Object.assign(window.WebSocket, WS);
const orig = HTMLCanvasElement.prototype.getContext;
HTMLCanvasElement.prototype.getContext = function(...a) {
  const ctx = orig.apply(this, a);
  if (ctx && (a[0] === 'webgl2' || a[0] === 'webgl') && !ctx.__wrapped) {
    ctx.__wrapped = true;
    const clear = ctx.clear.bind(ctx);
    ctx.clear = (m) => { if (m & ctx.COLOR_BUFFER_BIT) { const now = performance.now(); window.__n.clears++; if (now - window.__last > 30) { window.__n.frames++; window.__t.push(Math.round(now)); } window.__last = now; } clear(m); };
    const count = (name, idx) => {
      const f = ctx[name] && ctx[name].bind(ctx);
      if (!f) return;
      ctx[name] = (...args) => {
        window.__n.draws++;
        if (window.__n.frames === window.__snap) window.__calls.push([name, args[0], args[idx]]);
        if (args[0] === ctx.TRIANGLES) window.__n.tris += args[idx] / 3 * (name.includes('Instanced') ? args[args.length - 1] : 1);
        return f(...args);
      };
    };
    count('drawElements', 1); count('drawArrays', 2);
    count('drawElementsInstanced', 1); count('drawArraysInstanced', 2);
  }
  return ctx;
};
"""

env = {**os.environ, "NAVAPP_CACHE": os.environ.get("NAVAPP_CACHE", tempfile.mkdtemp()), "PYTHONUNBUFFERED": "1"}
w = tempfile.mkdtemp()
logp = w + "/s.log"
if WHAT in ("bare", "empty"):
    src = BARE.format(port=PORT)
    if WHAT == "empty":
        src = src.replace("s.scene.add_mesh_simple", "0 and s.scene.add_mesh_simple")
    cmd = [sys.executable, "-c", src]
    ready = None
else:
    cmd = [sys.executable, "-m", "navapp.cli", "serve", "--port", str(PORT), "--edge", "12", "--k", "12",
           "--session", w + "/sess"]
    ready = "Ready."
proc = subprocess.Popen(cmd, stdout=open(logp, "w"), stderr=subprocess.STDOUT, env=env)
try:
    while "viewer at" not in open(logp).read():
        if proc.poll() is not None:
            sys.exit(open(logp).read())
        time.sleep(0.5)
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path="/usr/bin/chromium", args=["--no-sandbox"])
        pg = b.new_page(viewport={"width": 1366, "height": 768})
        pg.add_init_script(INIT)
        pg.goto(f"http://127.0.0.1:{PORT}" + (f"/?{QUERY}" if QUERY else ""))
        if ready:
            pg.get_by_text(ready).first.wait_for(timeout=900_000)
        else:
            pg.locator("canvas").first.wait_for(timeout=60_000)
        hide = [x for x in os.environ.get("HIDE", "").split(",") if x]
        if hide:  # navapp's layers, unticked in its Layers panel
            pg.get_by_text("Layers and views").first.click()
            for name in hide:
                pg.get_by_label(name, exact=True).first.uncheck(force=True)
        time.sleep(8)
        print("visibility:", pg.evaluate("document.visibilityState"), "dpr:", pg.evaluate("window.devicePixelRatio"))
        for _ in range(2):
            procs = [q for q in psutil.Process().children(recursive=True) if "chrom" in q.name()]
            cpu0 = {q.pid: sum(q.cpu_times()[:2]) for q in procs}
            a = pg.evaluate("({...window.__n})")
            time.sleep(10)
            z = pg.evaluate("({...window.__n})")
            cpu1 = {q.pid: sum(q.cpu_times()[:2]) for q in procs if q.is_running()}
            tot = sum(cpu1[k] - cpu0[k] for k in cpu1)
            kinds: dict[str, float] = {}
            for q in procs:
                if q.pid in cpu1:
                    kind = next((c[7:] for c in q.cmdline() if c.startswith("--type=")), "browser")
                    kinds[kind] = kinds.get(kind, 0.0) + cpu1[q.pid] - cpu0[q.pid]
            d = {k: z[k] - a[k] for k in z}
            f = max(d["frames"], 1)
            print(f"{WHAT} {QUERY} {hide or ''}: 10 s idle: {d['frames']} frames ({d['clears'] / f:.0f} clears each), {d['draws'] / f:.0f} draw calls and "
                  f"{d['tris'] / f:.0f} triangles a frame, {d['ws']} websocket frames; chromium CPU {tot:.2f} s, "
                  f"{tot / f:.3f} s/frame", flush=True)
            print("  by process:", {k: round(v, 2) for k, v in kinds.items()})
        pg.evaluate("window.__snap = window.__n.frames + 1")
        time.sleep(2.5)
        print("  one frame's draw calls (call, mode, count):", pg.evaluate("window.__calls"))
        t = pg.evaluate("window.__t.slice(-40)")
        print("  last frames at (ms apart):", [b - a for a, b in zip(t, t[1:], strict=False)])
        if os.environ.get("SHOT"):
            pg.screenshot(path=os.environ["SHOT"])
        for ms, where in pg.evaluate("window.__intervals"):
            print(f"  setInterval({ms} ms) from {where}")
        b.close()
finally:
    proc.terminate()
    proc.wait(20)
